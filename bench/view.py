#!/usr/bin/env python
"""Frames per second that reach a client connected to stg-view, for lite and full models of N Gaussians.

    python bench/view.py [--gaussians 100000] [--size 640x360] [--seconds 10] [--device cpu|cuda]
                         [--client socket,browser] [--clients 1]

For each model kind and client it starts a `stg_runtime.viewer.Viewer` on the model
(stg_runtime.demo.random_model, bench/render.py --scene random), connects the client with a view of
--size, presses play, and counts the pictures that reach the client over --seconds, after --warmup
seconds of playing (numba's JIT); with --clients N, N clients at once (their FPS added up). It also
prints the Player's mean render time per frame on the server (with several clients, including the wait
for the others' renders).
The clients:

- browser: headless chromium (Debian's chromium and chromium-driver, through selenium) with a canvas of
  --size; the pictures are counted as viser's websocket worker hands them to the page. The browser
  draws every picture with software WebGL on the same cores as the server.
- socket: a client that speaks viser's websocket protocol from Python (`SocketClient`): it reports the
  browser's initial camera (training camera 0) and canvas size, receives the messages, and decodes every
  picture's JPEG. It stands for a browser on another machine (the usual set-up: an SSH tunnel to the
  server): it takes a few per cent of a core, so the server's cores are the Player's.

Needs the viewer extra, and for the browser client the browser: `python -m pip install -e
".[viewer,test]"`, `apt-get install -y chromium chromium-driver`.
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import threading
import time

import cv2
import msgspec
import numpy as np
import zstandard

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


def browser_missing() -> str | None:
    """Why the browser client cannot run here (no selenium, chromium or chromedriver), or None."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return 'no selenium (python -m pip install -e ".[viewer,test]")'
    absent = [name for name in ("chromium", "chromedriver") if shutil.which(name) is None]
    return f"no {' or '.join(absent)} (apt-get install -y chromium chromium-driver)" if absent else None


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


class BrowserClient:
    """Headless chromium showing the viewer with a canvas of width x height."""

    def __init__(self, viewer: Viewer, width: int, height: int):
        self.driver = browser(width, height)
        fit_window(self.driver, viewer.url, width, height)

    def picture_times(self) -> list[float]:
        """Seconds (browser clock) at which pictures reached the page since the last call."""
        return [ms / 1000 for ms in self.driver.execute_script("return window.__pictures.splice(0)")]

    def close(self) -> None:
        self.driver.quit()


class SocketClient:
    """A client of viser's websocket protocol in Python: it sends the camera a browser reports (the
    viewer's initial view with a canvas of width x height) and, on its own thread, receives the
    messages (16 bytes of sizes, zstd-compressed msgpack, then 8-byte aligned binary buffers) and
    decodes the JPEG of every picture (BackgroundImageMessage) as a browser must."""

    def __init__(self, viewer: Viewer, width: int, height: int):
        import viser
        from viser import _messages
        from websockets.sync.client import connect

        self.socket = connect(f"ws://{viewer.host}:{viewer.port}", max_size=None,
                              subprotocols=[f"viser-v{viser.__version__}"])
        pose = viewer._pose(viewer.player.cameras[0])
        camera = _messages.ViewerCameraMessage(
            wxyz=tuple(pose.wxyz), position=tuple(pose.position), fov=pose.fov, near=0.01, far=1000.0,
            image_height=height, image_width=width, look_at=tuple(pose.look_at),
            up_direction=tuple(pose.up_direction))
        self.socket.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        self._times: list[float] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        from websockets.exceptions import ConnectionClosed

        unzip = zstandard.ZstdDecompressor()
        try:
            for raw in self.socket:
                for jpeg in pictures(raw, unzip):
                    if cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) is None:
                        raise RuntimeError("a picture is not a JPEG")
                    with self._lock:
                        self._times.append(time.monotonic())
        except ConnectionClosed:
            pass

    def picture_times(self) -> list[float]:
        with self._lock:
            times, self._times = self._times, []
        return times

    def close(self) -> None:
        self.socket.close()
        self._thread.join(timeout=5)


def pictures(raw: bytes, unzip) -> list[bytes]:
    """The encoded pictures (BackgroundImageMessage rgb_data) in one websocket message of viser's."""
    size, packed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    batch = msgspec.msgpack.decode(unzip.decompress(raw[16:16 + packed], max_output_size=size))
    buffers, offset = [], 16 + packed
    for length in batch["binaryBufferLengths"]:
        offset += -offset % 8
        buffers.append(raw[offset:offset + length])
        offset += length
    found = []
    for message in batch["messages"]:
        data = message.get("rgb_data") if message["type"] == "BackgroundImageMessage" else None
        if isinstance(data, dict):  # a binary buffer's placeholder
            data = buffers[data["__binary_index"]]
        if data:
            found.append(bytes(data))
    return found


CLIENTS = {"browser": BrowserClient, "socket": SocketClient}


def rate(times: list[float]) -> float:
    """Pictures per second over arrival times (seconds)."""
    return (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0


def measure(kind: str, client_name: str, args, width: int, height: int) -> tuple[float, float, tuple]:
    """(FPS at the clients, all --clients together; mean server render ms; picture size) for one model
    kind and client."""
    model = random_model(args.gaussians, kind, width=width, height=height)
    viewer = Viewer(model, port=0, device=args.device,
                    settings=ViewSettings(max_pixels=width * height, preview_pixels=width * height))
    clients = []
    try:
        for _ in range(args.clients):
            clients.append(CLIENTS[client_name](viewer, width, height))
        viewer.playback.playing = True
        time.sleep(args.warmup)
        for client in clients:
            client.picture_times()
        renders = []
        start = time.monotonic()
        while time.monotonic() - start < args.seconds:
            time.sleep(0.1)
            renders += [s.stats.render_seconds for s in viewer.streams.values()]
        fps = sum(rate(client.picture_times()) for client in clients)
        stats = next(iter(viewer.streams.values())).stats
        size = (stats.camera.width, stats.camera.height) if stats.camera else (width, height)
        return fps, 1000 * float(np.mean(renders)) if renders else float("nan"), size
    finally:
        for client in clients:
            client.close()
        viewer.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", default="640x360", help="WxH of the browser's canvas (the pictures sent)")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds counted per model")
    ap.add_argument("--warmup", type=float, default=5.0, help="seconds of playing before counting")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--clients", type=int, default=1, help="clients connected at once (their FPS are added)")
    ap.add_argument("--client", default="socket,browser",
                    help="comma-separated clients: browser (headless chromium on this machine), socket "
                         "(viser's protocol from Python, standing for a browser on another machine)")
    args = ap.parse_args()
    clients = [c.strip() for c in args.client.split(",") if c.strip()]
    unknown = sorted(set(clients) - set(CLIENTS))
    if unknown or not clients:
        ap.error(f"--client takes {', '.join(CLIENTS)}; got {args.client!r}")
    if args.clients < 1:
        ap.error("--clients must be at least 1")
    missing = browser_missing()
    if "browser" in clients and missing:
        print(f"browser client skipped: {missing}")
        clients.remove("browser")
    if not clients:
        raise SystemExit(2)
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.2f}; device {args.device}")
    print(f"{args.gaussians} Gaussians, canvas {width}x{height}, playing, JPEG quality {ViewSettings().jpeg_quality}, "
          f"{args.clients} client{'s' * (args.clients > 1)} at once\n")
    print(f"{'model':<8}{'client':<9}{'picture':>10}{'FPS at the client':>19}{'render ms':>11}")
    for client in clients:
        for kind in ("lite", "full"):
            fps, render_ms, size = measure(kind, client, args, width, height)
            print(f"{kind:<8}{client:<9}{size[0]:>5}x{size[1]:<4}{fps:>19.1f}{render_ms:>11.1f}", flush=True)


if __name__ == "__main__":
    main()
