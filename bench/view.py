#!/usr/bin/env python
"""Frames per second that reach a browser connected to stg-view, for lite and full models of N Gaussians.

    python bench/view.py [--gaussians 100000] [--size 640x360] [--seconds 10] [--device cpu|cuda]

For each model kind it starts a `stg_runtime.viewer.Viewer` on the model (stg_runtime.demo.random_model,
the scene of bench/render.py), opens it in headless chromium (Debian's chromium and chromium-driver,
through selenium) with a canvas of --size, presses play, and counts the pictures that reach the page
(from viser's websocket worker) over --seconds, after --warmup seconds of playing (numba's JIT). It also
prints the Player's mean render time per frame on the server. Needs the viewer extra and the browser:
`python -m pip install -e ".[viewer,test]"`, `apt-get install -y chromium chromium-driver`.
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import time

import numpy as np

from stg_runtime.demo import random_model
from stg_runtime.viewer.frames import ViewSettings
from stg_runtime.viewer.server import Viewer

#: Run in the page before viser's scripts: records the arrival time (ms, performance.now()) of every
#: picture (BackgroundImageMessage) that viser's websocket worker hands to the page.
COUNT_PICTURES = """
window.__pictures = [];
const ViserWorker = window.Worker;
window.Worker = class extends ViserWorker {
  constructor(...args) {
    super(...args);
    this.addEventListener('message', (e) => {
      for (const m of (e.data && e.data.messages) || [])
        if (m.type === 'BackgroundImageMessage') window.__pictures.push(performance.now());
    });
  }
};
"""


def browser(width: int, height: int):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
                "--force-device-scale-factor=1"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": COUNT_PICTURES})
    return driver


def fit_window(driver, url: str, width: int, height: int) -> tuple[int, int]:
    """Open `url` and size the window so that the page's canvas is width x height; returns its size."""
    driver.set_window_size(width, height + 200)
    driver.get(url)
    time.sleep(2)
    for _ in range(3):
        w, h = driver.execute_script("return [window.innerWidth, window.innerHeight]")
        size = driver.get_window_size()
        driver.set_window_size(size["width"] + width - w, size["height"] + height - h)
        time.sleep(0.5)
    return tuple(driver.execute_script("return [window.innerWidth, window.innerHeight]"))


def picture_times(driver) -> list[float]:
    """Seconds (browser clock) at which pictures reached the page since the last call."""
    return [ms / 1000 for ms in driver.execute_script("return window.__pictures.splice(0)")]


def measure(kind: str, args, width: int, height: int) -> tuple[float, float, tuple]:
    """(FPS at the browser, mean server render ms, picture size) for one model kind."""
    model = random_model(args.gaussians, kind, width=width, height=height)
    viewer = Viewer(model, port=0, device=args.device,
                    settings=ViewSettings(max_pixels=width * height, preview_pixels=width * height))
    driver = browser(width, height)
    try:
        canvas = fit_window(driver, viewer.url, width, height)
        viewer.playback.playing = True
        time.sleep(args.warmup)
        picture_times(driver)
        renders = []
        start = time.monotonic()
        while time.monotonic() - start < args.seconds:
            time.sleep(0.1)
            renders += [s.stats.render_seconds for s in viewer.streams.values()]
        arrived = picture_times(driver)
        stats = next(iter(viewer.streams.values())).stats
        size = (stats.camera.width, stats.camera.height) if stats.camera else canvas
        fps = (len(arrived) - 1) / (arrived[-1] - arrived[0]) if len(arrived) > 1 else 0.0
        return fps, 1000 * float(np.mean(renders)), size
    finally:
        driver.quit()
        viewer.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", default="640x360", help="WxH of the browser's canvas (the pictures sent)")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds counted per model")
    ap.add_argument("--warmup", type=float, default=5.0, help="seconds of playing before counting")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.2f}; device {args.device}")
    print(f"{args.gaussians} Gaussians, canvas {width}x{height}, playing, JPEG quality {ViewSettings().jpeg_quality}\n")
    print(f"{'model':<8}{'picture':>10}{'FPS at the browser':>20}{'render ms':>11}")
    for kind in ("lite", "full"):
        fps, render_ms, size = measure(kind, args, width, height)
        print(f"{kind:<8}{size[0]:>5}x{size[1]:<4}{fps:>20.1f}{render_ms:>11.1f}")


if __name__ == "__main__":
    main()
