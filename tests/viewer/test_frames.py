"""The render callback (stg_runtime.viewer.frames): the image sent to a browser is Player.render for
the browser's camera, converted with viser's conventions, at the current time."""
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from stg_runtime import Player
from stg_runtime.video import to_uint8
from stg_runtime.viewer import frames
from stg_runtime.viewer.camera import camera_from_viser, viser_pose
from stg_runtime.viewer.frames import ClientStream, RenderThread, ViewSettings, render_image

VECTORS = Path(__file__).resolve().parents[2] / "formats" / "vectors"


class FakeClient:
    """What ClientStream reads of a viser ClientHandle: camera state and set_background_image."""

    def __init__(self, pose, width, height, client_id=-1):
        self.client_id = client_id
        self.camera = SimpleNamespace(wxyz=pose.wxyz, position=pose.position, fov=pose.fov,
                                      image_width=width, image_height=height)
        self.sent = []
        self.scene = SimpleNamespace(set_background_image=lambda image, **kw: self.sent.append((image, kw)))


@pytest.fixture(scope="module")
def player():
    return Player(VECTORS / "full.stg", device="cpu")


def test_image_sent_is_the_players_render(player):
    cam0 = player.cameras[0]
    pose = viser_pose(cam0)
    client = FakeClient(pose, cam0.width, cam0.height)
    t = float(player.frame_times()[3])
    stream = ClientStream(client, lambda: (player, 0, t), ViewSettings(jpeg_quality=95))
    assert stream.render_once(now=100.0)
    (image, options), = client.sent
    assert options == {"format": "jpeg", "jpeg_quality": 95}
    assert image.dtype == np.uint8 and image.shape == (cam0.height, cam0.width, 3)
    # the browser's camera is training camera 0: the same picture as Player.render from it
    np.testing.assert_array_equal(image, to_uint8(player.render(cam0, t)))
    # and in general, the camera made from viser's state with our conventions
    expected = camera_from_viser(pose.wxyz, pose.position, pose.fov, cam0.width, cam0.height)
    np.testing.assert_array_equal(image, to_uint8(player.render(expected, t)))
    assert not stream.render_once(now=101.0)  # nothing changed: nothing sent


def test_moving_camera_gets_a_preview_then_the_full_size(player):
    cam0 = player.cameras[0].resized(96, 64)
    client = FakeClient(viser_pose(cam0), 96, 64)
    settings = ViewSettings(max_pixels=96 * 64, preview_pixels=48 * 32)
    stream = ClientStream(client, lambda: (player, 0, 0.0), settings)
    assert stream.render_once(now=10.0)  # the first frame is full size
    assert client.sent[-1][0].shape == (64, 96, 3)
    client.camera.position = client.camera.position + [0.05, 0.0, 0.0]
    assert stream.render_once(now=10.1)  # moving: preview
    assert client.sent[-1][0].shape == (32, 48, 3) and stream.stats.preview
    assert not stream.render_once(now=10.2)  # still settling, nothing new
    assert stream.render_once(now=11.0)  # at rest: the full-size frame
    moved = camera_from_viser(client.camera.wxyz, client.camera.position, client.camera.fov, 96, 64)
    np.testing.assert_array_equal(client.sent[-1][0], to_uint8(player.render(moved, 0.0)))


def test_time_and_mode_changes_are_sent(player):
    cam0 = player.cameras[0]
    state = {"t": 0.0}
    settings = ViewSettings()
    client = FakeClient(viser_pose(cam0), cam0.width, cam0.height)
    stream = ClientStream(client, lambda: (player, 0, state["t"]), settings)
    stream.render_once(now=1.0)
    state["t"] = float(player.frame_times()[-1])
    assert stream.render_once(now=5.0)
    np.testing.assert_array_equal(client.sent[-1][0], to_uint8(player.render(cam0, state["t"])))
    settings.mode = "alpha"
    assert stream.render_once(now=6.0)
    alpha = player.render_all(cam0, state["t"]).alpha
    np.testing.assert_array_equal(client.sent[-1][0][..., 0], to_uint8(alpha[..., None])[..., 0])


def test_render_modes(player):
    cam, t = player.cameras[0], 0.2
    r = player.render_all(cam, t)
    depth = render_image(player, cam, t, "depth")
    covered = r.alpha > 0.5
    assert covered.any() and depth[~covered].max() == 0 and depth[covered].min() > 0
    # nearer is brighter
    near, far = np.unravel_index(np.argmin(np.where(covered, r.depth, np.inf)), r.depth.shape), \
        np.unravel_index(np.argmax(np.where(covered, r.depth, -np.inf)), r.depth.shape)
    assert depth[near][0] > depth[far][0]
    base = render_image(player, cam, t, "base colour").astype(float)
    expected = to_uint8(1 / (1 + np.exp(-r.features[..., :3].astype(np.float64))))  # full: sigmoid, no MLP
    assert np.abs(base - expected).max() <= 1
    assert not np.array_equal(base, render_image(player, cam, t, "rgb"))
    with pytest.raises(ValueError, match="render mode"):
        render_image(player, cam, t, "normals")


def test_streams_render_on_one_shared_thread(player, monkeypatch):
    # numba keeps an OpenMP pool per thread that starts parallel work: every browser's renders run
    # on the viewer's one RenderThread, whichever stream thread asks
    cam0 = player.cameras[0]
    renderer = RenderThread()
    threads = []

    def render(*args):
        threads.append(threading.get_ident())
        return render_image(*args)

    monkeypatch.setattr(frames, "render_image", render)
    clients = [FakeClient(viser_pose(cam0), cam0.width, cam0.height, client_id=i) for i in range(2)]
    streams = [ClientStream(c, lambda: (player, 0, 0.1), ViewSettings(), renderer) for c in clients]
    workers = [threading.Thread(target=s.render_once, kwargs={"now": 1.0}) for s in streams]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert len(threads) == 2 and len(set(threads)) == 1
    assert threads[0] not in {w.ident for w in workers} | {threading.get_ident()}
    for c in clients:
        np.testing.assert_array_equal(c.sent[-1][0], to_uint8(player.render(cam0, 0.1)))
    renderer.close()
    with pytest.raises(RuntimeError):
        renderer.run(render_image, player, cam0, 0.1)
