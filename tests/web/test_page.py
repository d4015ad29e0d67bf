"""The web player (stg_runtime/web) in real headless Chromium with software WebGL2 (SwiftShader): its
snapshot() matches Player.render at >= 40 dB for every test vector (lite with two segments, full, full
quantized, sh, full through a fisheye, two full segments crossfaded, format 1.4's compact encodings, 1.5's
arithmetic-coded ones) at 3 cameras x 3 times (and inside
each crossfade; there the frame loop's canvas too, and the crossfades of a streamed video); the depth
order follows time (two Gaussians crossing in depth); every malicious fixture, and fuzzed files the
Python reader refuses, end in a message in the page within 5 s; long videos stream by range requests; the controls work; and a
model exported with `stg-convert export-web`, served by `python -m http.server`, matches the Player.
The lowest PSNR is printed (pytest -s) and recorded in docs/web.md."""
from __future__ import annotations

import dataclasses
import json
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.web import page

pytestmark = pytest.mark.skipif(page.missing() is not None, reason=str(page.missing()))

from stg_runtime import Camera, Model, Player, Segment  # noqa: E402
from stg_runtime import format as stg_format  # noqa: E402
from stg_runtime.web.export import export_web  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
VECTORS = ROOT / "formats" / "vectors"
MALICIOUS = ROOT / "tests" / "runtime" / "malicious"
NAMES = ["lite", "full", "full_quantized", "sh", "full_fisheye", "full_crossfade", "full_compact", "full_ac"]
MIN_PSNR = 40.0


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A served folder: the exported player with full.stg, the other vectors, malicious/, a crossing scene."""
    folder = tmp_path_factory.mktemp("site")
    export_web(VECTORS / "full.stg", folder)
    for path in VECTORS.glob("*.stg"):
        shutil.copy(path, folder / path.name)
    shutil.copytree(MALICIOUS, folder / "malicious")
    stg_format.save(crossing_model(), folder / "crossing.stg")
    server = page.Server(folder)
    yield folder, server.url
    server.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = page.start_browser(tmp_path_factory.mktemp("chromium"))
    yield driver
    driver.quit()


def open_model(driver, url: str, name: str) -> None:
    driver.get(f"{url}index.html?model={name}")
    error = page.wait_ready(driver)
    assert error is None, error


def views(camera: Camera, target) -> list[Camera]:
    """The file's camera and two others looking at `target` from beside it (one at another size)."""
    out = [camera]
    centre, up = camera.center, -camera.R[1]
    distance = np.linalg.norm(target - centre)
    for k, (side, lift, size) in enumerate([(0.25, 0.1, (64, 40)), (-0.2, -0.15, None)]):
        eye = centre + distance * (side * camera.R[0] + lift * up)
        pose = Camera.look_at(eye, target, up, 40.0, camera.width, camera.height).world_to_camera
        moved = dataclasses.replace(camera, world_to_camera=pose, name=f"view{k + 1}")
        out.append(moved.resized(*size) if size else moved)
    return out


def times(player: Player) -> list[float]:
    """First frame, a middle time (in the second segment of a two-segment file) and the end; and inside
    each crossfade (format 1.3), where the later segment's weight is 1/8 and 1/2 (0.3 and 0.45 s in
    full_crossfade.stg)."""
    out = [player.start_time, player.start_time + 0.55 * player.duration, player.start_time + player.duration]
    for seg in player.model.segments:
        b = seg.crossfade_frames
        out += [(seg.start_frame - 0.5 - 0.5 * b + w * b) / player.fps for w in (0.125, 0.5) if b]
    return out


@pytest.mark.parametrize("path", ["points", "quads"])
@pytest.mark.parametrize("name", NAMES)
def test_vector_matches_the_player(site, browser, name, path):
    """Both splatting paths of renderer.js: point sprites (where the image fits the largest point
    size, as here) and the records with quads (else)."""
    folder, url = site
    player = Player(VECTORS / f"{name}.stg", device="cpu")
    open_model(browser, url, f"{name}.stg")
    browser.execute_script("window.stg.player.renderer.usePoints = arguments[0]", path == "points")
    target = player.model.segments[0].position[:, 0].mean(axis=0)
    values = []
    for camera in views(player.cameras[0], target):
        fits = browser.execute_script("return window.stg.player.renderer.pointsFit(arguments[0], arguments[1])",
                                      camera.width, camera.height)
        assert fits == (path == "points")
        for t in times(player):
            image = page.snapshot(browser, camera.to_dict(), t)
            assert image.shape == (camera.height, camera.width, 4)
            reference = player.render(camera, t)
            assert reference.std() > 0.01  # something to see
            values.append(page.psnr(image[..., :3], reference))
    print(f"\n{name} ({path}): PSNR {min(values):.2f} .. {max(values):.2f} dB over {len(values)} views")
    assert min(values) >= MIN_PSNR, values


def test_a_web_preset_file_matches_the_player(site, browser):
    """stg-convert compress --preset web (format 1.5: parts of acB / acB-delta arrays) of the demo model,
    played by the page and by the Player at the first frame and later, from the file's first camera."""
    from stg_runtime.demo import demo_model
    from stg_train.convert.compress import compress

    folder, url = site
    model, settings = compress(demo_model("full", num_frames=4), "web")
    assert any(":" in e for e in settings.encodings.values())
    assert any(stg_format.ac_bits(p.split(":")[0]) for e in settings.encodings.values() for p in e.split("+"))
    stg_format.save(model, folder / "demo.web.stg", **settings.save_kwargs())
    player = Player(folder / "demo.web.stg", device="cpu")
    open_model(browser, url, "demo.web.stg")
    camera = player.cameras[0].resized(160, 120)
    values = [page.psnr(page.snapshot(browser, camera.to_dict(), t)[..., :3], player.render(camera, t))
              for t in (0.0, 0.07)]
    print(f"\nweb preset: PSNR {min(values):.2f} .. {max(values):.2f} dB")
    assert min(values) >= MIN_PSNR, values


def box_edge_model() -> Model:
    """Thin Gaussians (lite, opacity 0.99, an identity camera at 140x96) whose footprint box is cut by
    the 3-sigma radius r = 6 pixels (3 sqrt(lambda_max) = 5.9): along the long axis the box's edges lie
    s = 0.002 .. 0.015 pixels beyond a pixel centre (the mean s from a pixel centre, each side, long
    axis along x and along y), and those centres take alpha ~0.01. So a quad drawn to the box with
    less margin than the rasterizer's snapping of its corners (1/16 pixel at WebGL2's minimum of 4
    subpixel bits) leaves them out. A fifth column holds thin Gaussians turned by 15-120 degrees (the
    oriented quads). None overlap."""
    fx, z, W, H = 100.0, 4.0, 140, 96
    long_axis = np.sqrt(((6 - 0.1) / 3) ** 2 - 0.3) * z / fx  # world sigma: 3 sqrt(lambda_max) = 5.9 pixels
    means, scales, quats = [], [], []
    for row in range(4):
        along_y, sign = row >= 2, (1, -1)[row % 2]
        for col in range(5):
            centre = np.array([28 * col + 14.5, 24 * row + 12.5])  # a pixel centre
            quat, scale = [1.0, 0.0, 0.0, 0.0], [long_axis, 0.01, 0.002]
            if col < 4:
                shift = sign * (0.002, 0.005, 0.01, 0.015)[col]
                centre += [0.3, shift] if along_y else [shift, 0.3]
                if along_y:
                    scale = [0.01, long_axis, 0.002]
            else:
                centre += 0.3  # (on a pixel centre, an integer radius would put centres on the box's edge)
                angle = np.radians((15, 35, 60, 120)[row])
                quat = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]
            means.append([(centre[0] - W / 2) * z / fx, (centre[1] - H / 2) * z / fx, z])
            scales.append(scale)
            quats.append(quat)
    n = len(means)
    seg = Segment(0, 10, opacity=np.full(n, 0.99, np.float32), t_center=np.full(n, 0.5, np.float32),
                  t_scale=np.zeros(n, np.float32), position=np.array(means, np.float32)[:, None],
                  rotation=np.array(quats, np.float32)[:, None], scale=np.array(scales, np.float32),
                  features=np.random.default_rng(0).uniform(0.2, 1.0, (n, 3)).astype(np.float32))
    return Model("lite", 10.0, [seg], cameras=[Camera(fx, fx, W / 2, H / 2, W, H, np.eye(4), "box edges")])


@pytest.mark.parametrize("path", ["points", "quads"])
def test_footprint_box_edges_match_the_player(site, browser, path):
    """Both splatting paths cover exactly the pixels of the Player's footprint rule (section 3: pixel
    centres with |dx| <= h_x, |dy| <= h_y), also centres a few thousandths of a pixel inside the box's
    edge: the float splat target (colour and alpha before the colour pass) against Player.render_all.
    With the quads' earlier margin of 0.01 pixel (now 1/8), SwiftShader's quads left out 16 such pixels
    here (alpha off by up to 0.0085)."""
    from stg_runtime.projection import camera_params, footprint
    folder, url = site
    model = box_edge_model()
    stg_format.save(model, folder / "box_edges.stg")
    player = Player(folder / "box_edges.stg", device="cpu")
    camera, seg = player.cameras[0], player.model.segments[0]
    # The scene does what it is for: along the long axes the Player's box (at most 6 pixels each side,
    # the radius) holds 12 pixel centres, the farthest 5.985 .. 5.998 pixels from the mean, where the
    # alpha reaches 0.005 or more.
    cam = camera_params(camera)
    arrays = [np.ascontiguousarray(a, np.float32) for a in (seg.position[:, 0], seg.rotation[:, 0], seg.scale, seg.opacity)]
    reference = player.render_all(camera, 0.5)
    for i in [i for i in range(seg.count) if i % 5 < 4]:
        _, u, v, *_, u0, u1, v0, v1 = footprint(cam, camera.width, camera.height, *arrays, i)
        mean, lo, hi = (v, v0, v1) if i >= 10 else (u, u0, u1)
        far = max(hi + 0.5 - mean, mean - lo - 0.5)
        assert hi - lo == 11 and 5.98 < far < 6.0, (i, lo, hi, far)
        end = hi if hi + 0.5 - mean > mean - lo - 0.5 else lo
        edge = reference.alpha[v0:v1 + 1, end] if i < 10 else reference.alpha[end, u0:u1 + 1]
        assert edge.max() > 0.005, (i, edge)
    open_model(browser, url, "box_edges.stg")
    browser.execute_script("window.stg.player.renderer.usePoints = arguments[0]", path == "points")
    splat = page.splat_target(browser, camera.to_dict(), 0.5)
    expect = np.concatenate([reference.features, reference.alpha[..., None]], axis=-1)
    diff = np.abs(splat - expect)
    print(f"\nbox edges ({path}): {int((diff > 1e-5).sum())} values differ by more than 1e-5, at most {diff.max():.2g}")
    assert diff.max() <= 1e-4, f"{int((diff[..., 3] > 1e-4).sum())} pixels' alpha off, by up to {diff[..., 3].max():.4f}"


CANVAS_PIXELS = """
const [cam, t, done] = arguments, p = window.stg.player, gl = p.renderer.gl;
p.pause();
p.setCamera(cam);
p.setTime(t);
p.sortedFor = null;   // so that the frame loop sorts again for this view and time
p.continuous = true;  // and draws every frame
const end = performance.now() + 60000;
let sorted = false;
const step = () => {  // an animation frame callback: it runs after the player's tick of the same frame
  if (p.error || performance.now() > end) { p.continuous = false; done({error: p.error || "timed out"}); return; }
  if (!sorted) {  // this frame's sorts answered: the next tick draws with their orders
    sorted = p.sortedFor !== null && !p.inFlight;
    requestAnimationFrame(step);
    return;
  }
  p.continuous = false;
  const W = p.cam.width, H = p.cam.height, pixels = new Uint8Array(4 * W * H);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.readPixels(0, 0, W, H, gl.RGBA, gl.UNSIGNED_BYTE, pixels);  // the canvas, bottom row first
  let text = "";
  for (let i = 0; i < pixels.length; i += 0x8000) text += String.fromCharCode(...pixels.subarray(i, i + 0x8000));
  done({width: W, height: H, data: btoa(text)});
};
requestAnimationFrame(step);
"""


def canvas_pixels(driver, camera: dict, t: float) -> np.ndarray:
    """(H, W, 4) uint8 of what the frame loop drew on the canvas for `camera` at time t (not snapshot())."""
    import base64
    result = driver.execute_async_script(CANVAS_PIXELS, camera, t)
    if "error" in result:
        raise AssertionError(f"canvas read failed: {result['error']}")
    data = np.frombuffer(base64.b64decode(result["data"]), np.uint8).reshape(result["height"], result["width"], 4)
    return data[::-1]


def test_crossfade_on_the_canvas(site, browser):
    """The frame loop inside a crossfade (format 1.3): both segments sorted and drawn, blended on the
    canvas as Player.render blends them; before it, one segment."""
    folder, url = site
    player = Player(VECTORS / "full_crossfade.stg", device="cpu")
    open_model(browser, url, "full_crossfade.stg")
    camera = views(player.cameras[0], player.model.segments[0].position[:, 0].mean(axis=0))[1]
    for t, parts in ((0.45, 2), (0.62, 2), (0.1, 1), (0.3, 2)):
        assert len(player.model.segments_at(t)) == parts
        image = canvas_pixels(browser, camera.to_dict(), t)
        assert image.shape == (camera.height, camera.width, 4)
        assert page.psnr(image[..., :3], player.render(camera, t)) >= MIN_PSNR, t


def crossing_model() -> Model:
    """Two large Gaussians on the axis of an identity camera, red moving away (depth 2 -> 4) and blue
    coming closer (4 -> 2) over the segment: they cross at tau = 0.5."""
    n = 2
    position = np.zeros((n, 2, 3), np.float32)
    position[:, 0] = [[0.05, 0.0, 3.0], [-0.05, 0.0, 3.0]]
    position[:, 1] = [[0.0, 0.0, 2.0], [0.0, 0.0, -2.0]]
    rotation = np.zeros((n, 1, 4), np.float32)
    rotation[:, 0, 0] = 1
    seg = Segment(0, 10, opacity=np.full(n, 0.9, np.float32), t_center=np.full(n, 0.5, np.float32),
                  t_scale=np.zeros(n, np.float32), position=position, rotation=rotation,
                  scale=np.full((n, 3), 0.3, np.float32), features=np.array([[1, 0, 0], [0, 0, 1]], np.float32))
    camera = Camera(40.0, 40.0, 32.0, 24.0, 64, 48, np.eye(4), "axis")
    return Model("lite", 10.0, [seg], cameras=[camera])


def test_depth_order_follows_time(site, browser):
    folder, url = site
    player = Player(folder / "crossing.stg", device="cpu")
    camera = player.cameras[0]
    open_model(browser, url, "crossing.stg")
    centre = {}
    for t in (0.2, 0.8, 0.2):  # and back: the order is sorted again for every time
        image = page.snapshot(browser, camera.to_dict(), t)
        reference = player.render(camera, t)
        assert page.psnr(image[..., :3], reference) >= MIN_PSNR, t
        centre[t] = image[24, 32, :3].astype(int)
    assert centre[0.2][0] > centre[0.2][2] + 60  # red in front before the crossing
    assert centre[0.8][2] > centre[0.8][0] + 60  # blue in front after it


def wait_message(driver, timeout: float) -> tuple[str | None, bool, str]:
    """(the page's error or None, whether the load finished, the text shown in #message) within timeout."""
    end = time.monotonic() + timeout
    while True:
        state = driver.execute_script(
            "const s = window.stg || {}; return [s.error || null, !!s.player && !!s.player.model, "
            "document.getElementById('message').textContent];")
        if state[0] or state[1] or time.monotonic() > end:
            return tuple(state)
        time.sleep(0.05)


@pytest.mark.parametrize("name", sorted(json.loads((MALICIOUS / "index.json").read_text())))
def test_malicious_file_ends_in_a_message(site, browser, name):
    folder, url = site
    expect = json.loads((MALICIOUS / "index.json").read_text())[name]
    start = time.monotonic()
    browser.get(f"{url}index.html?model=malicious/{name}")
    error, loaded, shown = wait_message(browser, 5.0)
    elapsed = time.monotonic() - start
    if expect["expect"] == "loads":
        assert loaded and error is None, (error, shown)
        image = page.snapshot(browser)
        assert image[..., :3].max() > 0
        return
    assert error is not None and elapsed < 5.0, (name, elapsed, shown)
    assert shown == error and error.startswith(f"{name}: ") and re.search(expect["match"], error), error


@pytest.mark.parametrize("case", ["missing", "truncated"])
def test_damaged_or_missing_file_ends_in_a_message(site, browser, case):
    folder, url = site
    if case == "truncated":
        (folder / "cut.stg").write_bytes((VECTORS / "full.stg").read_bytes()[:-1000])
    browser.get(f"{url}index.html?model={'cut.stg' if case == 'truncated' else 'nothing.stg'}")
    error, loaded, shown = wait_message(browser, 5.0)
    want = "checksum mismatch" if case == "truncated" else "nothing.stg: HTTP 404"
    assert error and want in error and shown == error, error


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_exported_demo_model_served_by_http_server(tmp_path, browser):
    """End to end: the runtime's demo model (stg_runtime.demo.demo_model, full, the scene `stg-train --demo`
    learns; a trained model would take minutes of CI), exported with stg-convert export-web and served by
    `python -m http.server`."""
    from stg_runtime.demo import demo_model
    from stg_train.cli.convert import main as convert_main
    model_path = tmp_path / "demo.stg"
    stg_format.save(demo_model("full", num_frames=30), model_path)
    site = tmp_path / "site"
    assert convert_main(["export-web", str(model_path), str(site)]) == 0
    assert (site / "index.html").is_file() and (site / "demo.stg").read_bytes() == model_path.read_bytes()
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1", "-d", str(site)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(100):
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        browser.get(f"http://127.0.0.1:{port}/")
        assert page.wait_ready(browser) is None
        player = Player(model_path, device="cpu")
        for t in (0.0, 0.5):
            image = page.snapshot(browser, None if t == 0.0 else player.cameras[3].to_dict(), t)
            camera = player.cameras[0 if t == 0.0 else 3]
            value = page.psnr(image[..., :3], player.render(camera, t))
            print(f"\nexported demo model, camera {camera.name}, t = {t}: {value:.2f} dB")
            assert value >= MIN_PSNR
    finally:
        server.terminate()
        server.wait(timeout=10)


def long_video() -> Model:
    """Four segments of 10 frames (the demo scene with different seeds), lite, at 10 fps."""
    from stg_runtime.demo import demo_model
    segments = []
    for k in range(4):
        s = demo_model("lite", fps=10.0, num_frames=10, seed=k).segments[0]
        segments.append(Segment(10 * k, 10, **s.arrays()))
    return Model("lite", 10.0, segments, cameras=demo_model("lite", fps=10.0, num_frames=10).cameras[:1])


def long_crossfaded_video() -> Model:
    """long_video with a crossfade of 4 frames into each of segments 1-3 (format 1.3)."""
    from dataclasses import replace
    model = long_video()
    segments = [model.segments[0]] + [replace(s, crossfade_frames=4) for s in model.segments[1:]]
    return Model("lite", model.fps, segments, cameras=model.cameras)


@pytest.fixture(scope="module")
def ranged_site(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ranged")
    export_web(VECTORS / "lite.stg", folder)
    model = long_video()
    stg_format.save(model, folder / "long.stg")
    stg_format.save(long_crossfaded_video(), folder / "long_crossfade.stg")
    stg_format.save(model, folder / "raw.stg", codec="raw")
    stg_format.save(model, folder / "long_compact.stg",  # format 1.4: parts, codebooks, differences
                    encodings={"opacity": "vq/u8", "position": "u16-delta:3+vq/f16:9",
                               "features": "u8-delta:1+vq/u8:2"})
    stg_format.save(model, folder / "long_ac.stg",  # format 1.5: arithmetic-coded arrays, parts, a codebook
                    encodings={"opacity": "ac16", "t_center": "ac16-delta", "t_scale": "ac16", "rotation": "ac16",
                               "scale": "ac16-delta", "position": "ac16-delta:3+vq/ac16:9",  # (117 kB: the first
                               "features": "ac16:1+ac12-delta:2"})  # 64 KiB do not hold segment 0 and 1)
    data = bytearray((folder / "raw.stg").read_bytes())
    data[-40] ^= 0xFF  # the low byte of a float of the last segment (stored raw): only the checksum can tell
    (folder / "long_damaged.stg").write_bytes(bytes(data))
    from stg_runtime.demo import demo_model
    stg_format.save(demo_model("full", num_frames=10), folder / "one.stg", codec="raw")  # one segment, > 64 KiB
    server = page.Server(folder, page.RangeHandler)
    yield folder, server.url
    server.close()


def test_long_video_streams_segments(ranged_site, browser):
    """Segments arrive by range requests: the first frame shows before the whole file has arrived, every
    segment matches the Player, and once every byte is in the checksum is verified."""
    folder, url = ranged_site
    player = Player(folder / "long.stg", device="cpu")
    camera = player.cameras[0]
    page.RangeHandler.sent.clear()
    open_model(browser, url, "long.stg")
    image = page.snapshot(browser, camera.to_dict(), 0.0)
    assert page.psnr(image[..., :3], player.render(camera, 0.0)) >= MIN_PSNR
    sent = sum(n for path, n in page.RangeHandler.sent if path == "/long.stg")
    size = (folder / "long.stg").stat().st_size
    assert sent < 0.75 * size, (sent, size)  # segment 0 and the one ahead, not the rest
    for t in (1.5, 2.5, 3.95, 0.5):
        image = page.snapshot(browser, camera.to_dict(), t)
        assert page.psnr(image[..., :3], player.render(camera, t)) >= MIN_PSNR, t
    sent = sum(n for path, n in page.RangeHandler.sent if path == "/long.stg")
    assert sent == size, page.RangeHandler.sent  # every byte once
    assert browser.execute_script("return [window.stg.player.file.checked, window.stg.error]") == [True, None]


@pytest.mark.parametrize("name", ["long_compact.stg", "long_ac.stg"])
def test_long_compact_video_streams_segments(ranged_site, browser, name):
    """A format 1.4 file (parts, codebooks, differences) or 1.5 file (arithmetic-coded arrays, their
    blobs ordinary data blobs) streams as a 1.3 one: the first frame needs its segment's bytes (with
    their codebooks and parts) and the one ahead, not the rest."""
    folder, url = ranged_site
    player = Player(folder / name, device="cpu")
    camera = player.cameras[0]
    page.RangeHandler.sent.clear()
    open_model(browser, url, name)
    image = page.snapshot(browser, camera.to_dict(), 0.0)
    assert page.psnr(image[..., :3], player.render(camera, 0.0)) >= MIN_PSNR
    sent = sum(n for path, n in page.RangeHandler.sent if path == f"/{name}")
    size = (folder / name).stat().st_size
    assert sent < 0.75 * size, (sent, size)
    for t in (3.95, 2.5):  # the last segment first: its first blob (a codebook) lies past the one before
        image = page.snapshot(browser, camera.to_dict(), t)
        assert page.psnr(image[..., :3], player.render(camera, t)) >= MIN_PSNR, t
    assert browser.execute_script("return [window.stg.player.file.checked, window.stg.error]") == [True, None]


def test_long_crossfaded_video_streams_segments(ranged_site, browser):
    """Crossfades across segments that arrive by range requests (both segments of a fade fetched, the
    earlier one also when the playhead jumps back into a fade-in), each time matching the Player."""
    folder, url = ranged_site
    player = Player(folder / "long_crossfade.stg", device="cpu")
    camera = player.cameras[0]
    open_model(browser, url, "long_crossfade.stg")
    for t in (0.0, 0.95, 2.0, 3.0, 1.05, 2.5):
        image = page.snapshot(browser, camera.to_dict(), t)
        assert page.psnr(image[..., :3], player.render(camera, t)) >= MIN_PSNR, t
    assert sum(len(player.model.segments_at(t)) == 2 for t in (0.95, 2.0, 3.0, 1.05)) == 4
    assert browser.execute_script("return window.stg.error") is None


def test_long_video_with_a_damaged_segment_ends_in_a_message(ranged_site, browser):
    folder, url = ranged_site
    open_model(browser, url, "long_damaged.stg")
    page.snapshot(browser, None, 0.0)  # the first segment plays
    with pytest.raises(AssertionError, match="checksum mismatch"):
        for t in (1.5, 2.5, 3.5):
            page.snapshot(browser, None, t)
    error, loaded, shown = wait_message(browser, 5.0)
    assert error and "long_damaged.stg: checksum mismatch" in error and shown == error


def test_page_controls(site, browser):
    """The page's controls: play advances the time, a preset sets a training camera, a drag orbits, the
    W key flies forward, the FPS readout counts."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select
    folder, url = site
    open_model(browser, url, "full.stg")
    state = "const p = window.stg.player; return [p.time, p.camera.world_to_camera, p.playing];"
    t0, pose0, _ = browser.execute_script(state)
    browser.find_element(By.ID, "play").click()
    time.sleep(0.6)
    browser.find_element(By.ID, "play").click()
    t1, _, playing = browser.execute_script(state)
    assert t1 > t0 and not playing
    canvas = browser.find_element(By.ID, "view")
    ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(40, 10).release().perform()
    _, pose1, _ = browser.execute_script(state)
    assert not np.allclose(pose0, pose1)
    rotation = np.array(pose1).reshape(4, 4)[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)  # still a rotation
    centre = lambda pose: -np.array(pose).reshape(4, 4)[:3, :3].T @ np.array(pose).reshape(4, 4)[:3, 3]  # noqa: E731
    ActionChains(browser).key_down("w", canvas).pause(0.4).key_up("w", canvas).perform()
    _, pose2, _ = browser.execute_script(state)
    forward = np.array(pose1).reshape(4, 4)[2, :3]
    assert np.dot(centre(pose2) - centre(pose1), forward) > 0  # moved forward
    select = Select(browser.find_element(By.ID, "presets"))
    assert len(select.options) == len(Player(VECTORS / "full.stg", device="cpu").cameras)
    select.select_by_index(len(select.options) - 1)
    browser.find_element(By.ID, "reset").click()
    assert browser.execute_script("return window.stg.player.camera") == \
        browser.execute_script("return window.stg.player.cameras.at(-1)")
    assert re.fullmatch(r"\d+\.\d fps", browser.find_element(By.ID, "fps").text)


def test_fuzzed_files_refused_by_python_end_in_a_message(tmp_path, browser):
    """Mutated files (tools/fuzz.py's mutations, checksums recomputed) that the Python reader refuses
    end in a message in the page within 5 s each."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from fuzz import mutate_stg
    finally:
        sys.path.remove(str(ROOT / "tools"))
    from stg_runtime import FormatError
    export_web(VECTORS / "full.stg", tmp_path)
    rng = np.random.default_rng(5)
    bases = [p.read_bytes() for p in sorted(VECTORS.glob("*.stg"))]
    refused = []
    while len(refused) < 12:
        _, data = mutate_stg(bases[len(refused) % len(bases)], rng)
        path = tmp_path / f"fuzz{len(refused):02d}.stg"
        path.write_bytes(data)
        try:
            stg_format.load(path)
        except FormatError:
            refused.append(path.name)
    server = page.Server(tmp_path)
    try:
        for name in refused:
            start = time.monotonic()
            browser.get(f"{server.url}index.html?model={name}")
            error, loaded, shown = wait_message(browser, 5.0)
            assert error and error.startswith(f"{name}: ") and shown == error, (name, error, shown)
            assert time.monotonic() - start < 5.0
    finally:
        server.close()


def test_one_segment_file_from_a_range_server(ranged_site, browser):
    """A one-segment file larger than the first range: the rest in one request, checked as a whole."""
    folder, url = ranged_site
    player = Player(folder / "one.stg", device="cpu")
    page.RangeHandler.sent.clear()
    open_model(browser, url, "one.stg")
    image = page.snapshot(browser, player.cameras[0].to_dict(), 0.2)
    assert page.psnr(image[..., :3], player.render(player.cameras[0], 0.2)) >= MIN_PSNR
    size = (folder / "one.stg").stat().st_size
    assert size > 65536 and sum(n for path, n in page.RangeHandler.sent if path == "/one.stg") == size


def test_embedding_snippet_of_the_docs_plays(tmp_path, browser):
    """docs/web.md's embedding example, as written, in a page beside an exported site/: the canvas shows
    the model."""
    import io

    import imageio.v3 as iio
    from selenium.webdriver.common.by import By
    blocks = re.findall(r"(?ms)^```html\n(.*?)^```", (ROOT / "docs" / "web.md").read_text())
    snippet = next(b for b in blocks if "StgPlayer" in b)
    model = tmp_path / "model.stg"
    shutil.copy(VECTORS / "full.stg", model)
    export_web(model, tmp_path / "site")
    (tmp_path / "embed.html").write_text(f"<!doctype html>\n<html><body style='margin:0'>\n{snippet}</body></html>\n")
    server = page.Server(tmp_path)
    try:
        browser.get(f"{server.url}embed.html")
        canvas = browser.find_element(By.ID, "scene")
        for _ in range(100):
            shot = iio.imread(io.BytesIO(canvas.screenshot_as_png))[..., :3]
            if shot.max() > 50:
                break
            time.sleep(0.1)
        assert shot.max() > 50 and shot.std() > 5, "the embedded canvas stayed blank"
    finally:
        server.close()
