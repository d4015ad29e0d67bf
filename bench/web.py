#!/usr/bin/env python
"""The web player's figures (docs/web.md): frames per second in headless Chromium with software WebGL2
(SwiftShader) beside the CPU Player's in the same run, the time from page load to the first frame over
localhost, and the bytes transferred.

    python bench/web.py [--scene like-trained|random] [--gaussians 100000] [--size 640x360] [--seconds 6]

For each kind (lite, full): the benchmark model (stg_runtime.demo.like_trained_model, or random_model,
as bench/render.py) is exported with stg_runtime.web.export.export_web and served from a local HTTP
server that counts the bytes it sends. The page is opened fresh; figures:
- first frame: ms from the start of navigation (performance.timeOrigin) to the first frame drawn on the
  canvas, which includes fetching, checking (SHA-256) and decoding the file and the first depth sort;
- page FPS: frames drawn per second while playing (the time changes every frame, so every frame is
  sorted again in the worker, concurrently), over --seconds, by the page's path; quads FPS: the same
  by the records and quads (renderer.usePoints = false), right after;
- draw ms: the median time of one complete frame (time evaluation, splatting, colour, read back), the
  sort excluded, by the page's path (point sprites where the image fits the largest point size);
  quads ms: the same by the other path (records and quads), alternating with it; and the worker's
  sort time;
- CPU Player FPS: Player(device="cpu").render at a new time per frame (median of 10), this process;
- bytes: the model's bytes the page fetched, against the .stg's size, and the page's own files;
- the scene's load (stg_runtime.render_load) at two times: the pixel contributions of every Gaussian's
  footprint (what the page blends) and those before each pixel's transmittance stop (what the CPU
  Player composites): what the stop could save.
Chromium and the Player take turns (never at the same time), on the same cores.
"""
from __future__ import annotations

import argparse
import functools
import http.server
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stg_runtime import Player  # noqa: E402
from stg_runtime import format as stg_format  # noqa: E402
from stg_runtime.demo import like_trained_model, random_model  # noqa: E402
from stg_runtime.render_load import scene_load  # noqa: E402
from stg_runtime.web.export import export_web  # noqa: E402
from tests.web import page  # noqa: E402


class CountingHandler(http.server.SimpleHTTPRequestHandler):
    sent: dict = {}  # path -> bytes sent

    def log_message(self, *args):
        pass

    def copyfile(self, source, outputfile):
        data = source.read()
        type(self).sent[self.path] = type(self).sent.get(self.path, 0) + len(data)
        outputfile.write(data)


def describe_machine() -> str:
    try:
        sys.path.insert(0, str(ROOT / "bench"))
        from machine import describe
        return describe()
    except Exception:  # noqa: BLE001 - the machine line is informative only
        import platform
        return platform.processor() or platform.machine()


def cpu_fps(path: Path) -> float:
    player = Player(path, device="cpu")
    camera = player.cameras[0]
    times = np.linspace(player.start_time, player.start_time + player.duration * 0.9, 11)
    player.render(camera, float(times[0]))  # compile, warm up
    seconds = []
    for t in times[1:]:
        start = time.perf_counter()
        player.render(camera, float(t))
        seconds.append(time.perf_counter() - start)
    return 1.0 / float(np.median(seconds))


PAGE_FIGURES = """
const [seconds, done] = arguments;
const p = window.stg.player, r = p.renderer, gl = r.gl;
const first = p.stats.firstFrameMs;
// the page's FPS while playing, by its path (point sprites where they fit), then by the quads
const play = async () => {
  p.continuous = true; p.play();
  await new Promise((ok) => setTimeout(ok, 1000));
  const start = performance.now(), frames0 = p.framesTotal;
  await new Promise((ok) => setTimeout(ok, 1000 * seconds));
  p.pause(); p.continuous = false;
  return (p.framesTotal - frames0) / ((performance.now() - start) / 1000);
};
const fps = await play();
r.usePoints = false;
const quadFps = await play();
r.usePoints = true;
// one frame's draw, sort excluded
const {gpu, tau} = p.current();
const draws = [];
const quadDraws = [];
for (let i = 0; i < 7; i++) {  // alternately: the default path (point sprites where they fit), the quads
  for (const [points, list] of [[true, draws], [false, quadDraws]]) {
    r.usePoints = points;
    gl.finish(); const t0 = performance.now(); r.draw(gpu, p.cam, tau, 'pixels'); list.push(performance.now() - t0);
  }
}
r.usePoints = true;
draws.sort((a, b) => a - b);
quadDraws.sort((a, b) => a - b);
done({first, fps, quadFps, drawMs: draws[3], quadDrawMs: quadDraws[3], points: r.pointsFit(p.cam.width, p.cam.height),
      sortMs: p.sortMs, instances: gpu.instances, floatBlend: r.floatBlend});
"""


def page_figures(driver, url: str, seconds: float) -> dict:
    driver.get(url)
    error = page.wait_ready(driver, timeout=300)
    if error:
        raise SystemExit(f"the page failed: {error}")
    deadline = time.monotonic() + 300
    while driver.execute_script("return window.stg.player.stats.firstFrameMs") is None:
        if time.monotonic() > deadline:
            raise SystemExit("no frame within 300 s")
        time.sleep(0.05)
    return driver.execute_async_script(f"(async () => {{ {PAGE_FIGURES} }})(...arguments)", seconds)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=["like-trained", "random"], default="like-trained")
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--seconds", type=float, default=6.0, help="how long the page plays for its FPS")
    args = ap.parse_args(argv)
    if page.missing():
        raise SystemExit(f"bench/web.py {page.missing()}")
    width, height = map(int, args.size.split("x"))
    print(f"machine: {describe_machine()}")
    print(f"scene: {args.scene}, {args.gaussians} Gaussians, {width}x{height}; Chromium with SwiftShader (software "
          f"WebGL2), no GPU")
    print(f"load average: {os.getloadavg()[0]:.2f} at the start")
    print(f"{'kind':5} {'first frame ms':>14} {'page FPS':>9} {'quads FPS':>9} {'draw ms':>8} {'quads ms':>8} {'sort ms':>8} {'CPU FPS':>8} "
          f"{'page/CPU':>8} {'quads/CPU':>9} {'model bytes':>11} {'.stg size':>10} {'page bytes':>10}")
    work = Path(tempfile.mkdtemp(prefix="stg-web-bench-"))
    loads = []
    driver = page.start_browser(work / "chromium")
    try:
        for kind in ("lite", "full"):
            make = like_trained_model if args.scene == "like-trained" else random_model
            model = make(args.gaussians, width=width, height=height, kind=kind)
            site = work / kind
            site.mkdir()
            stg_format.save(model, site / "bench.stg", codec="raw")
            export_web(site / "bench.stg", site)
            CountingHandler.sent = {}
            server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(CountingHandler, directory=str(site)))
            threading.Thread(target=server.serve_forever, daemon=True).start()
            try:
                figures = page_figures(driver, f"http://127.0.0.1:{server.server_address[1]}/", args.seconds)
            finally:
                server.shutdown()
                server.server_close()
            sent = dict(CountingHandler.sent)
            cpu = cpu_fps(site / "bench.stg")
            size = (site / "bench.stg").stat().st_size
            loads.append((kind, model))
            print(f"{kind:5} {figures['first']:14.0f} {figures['fps']:9.2f} {figures['quadFps']:9.2f} {figures['drawMs']:8.1f} {figures['quadDrawMs']:8.1f} "
                  f"{figures['sortMs']:8.1f} {cpu:8.2f} {figures['fps'] / cpu:8.2f} {figures['quadFps'] / cpu:9.2f} {sent.get('/bench.stg', 0):11d} "
                  f"{size:10d} {sum(sent.values()) - sent.get('/bench.stg', 0):10d}")
    finally:
        driver.quit()
    for kind, model in loads:  # what the transmittance stop could save: contributions after it
        for t in (0.0, 0.5 * model.duration):
            load = scene_load(model, model.cameras[0], t)
            blended, kept = int(load.footprints.sum()), int(load.layers.sum())
            print(f"{kind} at t = {t:.2f} s: {load.summary()}; {blended} pixel contributions blended without the stop, "
                  f"{kept} before it ({100 * (blended - kept) / max(blended, 1):.3f}% after it)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
