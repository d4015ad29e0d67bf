"""Driving the web player in real headless Chromium (selenium; .ci/run installs chromium and
chromium-driver): a static server for a folder, the browser, and the page's window.stg API."""
from __future__ import annotations

import base64
import functools
import http.server
import io
import os
import re
import shutil
import socketserver
import tempfile
import threading
from pathlib import Path

import numpy as np

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
#: Software WebGL2 in headless Chromium (SwiftShader through ANGLE), without a GPU.
FLAGS = ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--window-size=800,600")


def missing() -> str | None:
    """Why the browser tests cannot run here, or None."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "needs selenium"
    if not (CHROMIUM and DRIVER):
        return "needs chromium and chromium-driver (apt)"
    return None


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


class RangeHandler(_Quiet):
    """A static server that also answers `Range: bytes=A-B` with 206 (as nginx, Apache or any CDN do;
    Python's http.server does not), and records what it sent: (path, bytes) per response."""

    sent: list = []

    def send_head(self):
        path = self.translate_path(self.path)
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", (self.headers.get("Range") or "").strip())
        if not match or not os.path.isfile(path):
            head = super().send_head()
            if head is not None and os.path.isfile(path):
                type(self).sent.append((self.path, os.path.getsize(path)))
            return head
        size = os.path.getsize(path)
        start, end = int(match[1]), min(int(match[2]) if match[2] else size - 1, size - 1)
        if start >= size:
            self.send_error(416)
            return None
        with open(path, "rb") as f:
            f.seek(start)
            data = f.read(end - start + 1)
        self.send_response(206)
        self.send_header("Content-Type", self.guess_type(path))
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        type(self).sent.append((self.path, len(data)))
        return io.BytesIO(data)


class Server:
    """`python -m http.server` for `folder` on a free localhost port, in a thread."""

    def __init__(self, folder: Path, handler=_Quiet):
        socketserver.TCPServer.allow_reuse_address = True
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=str(folder)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def start_browser(user_data: Path | None = None):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={user_data or tempfile.mkdtemp(prefix='stg-web-chromium-')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    driver.set_script_timeout(180)
    return driver


def wait_ready(driver, timeout: float = 60.0) -> str | None:
    """Wait for the page's first load; its error message, or None. AssertionError with the page's
    console when the page does not start."""
    result = driver.execute_async_script(
        "const [timeout, done] = arguments, end = performance.now() + 1000 * timeout;"
        "const wait = () => window.stg && window.stg.ready ? window.stg.ready.then(() => done([window.stg.error]))"
        " : performance.now() > end ? done(null) : setTimeout(wait, 20);"
        "wait();", timeout)
    if result is None:
        logs = "\n".join(entry["message"] for entry in driver.get_log("browser"))
        raise AssertionError(f"the page did not start within {timeout} s; its console:\n{logs}")
    return result[0]


def snapshot(driver, camera: dict | None = None, t: float | None = None) -> np.ndarray:
    """(H, W, 4) uint8 of window.stg.snapshot() after setCamera(camera) and setTime(t)."""
    result = driver.execute_async_script(
        "const [cam, t, done] = arguments;"
        "try { if (cam) window.stg.setCamera(cam); if (t !== null) window.stg.setTime(t);"
        " window.stg.snapshotBase64().then(done, (e) => done({error: String(e)})); } catch (e) { done({error: String(e)}); }",
        camera, t)
    if "error" in result:
        raise AssertionError(f"snapshot failed: {result['error']}")
    data = np.frombuffer(base64.b64decode(result["data"]), np.uint8)
    return data.reshape(result["height"], result["width"], 4)


SPLAT_TARGET = """
const [cam, t, done] = arguments, r = window.stg.player.renderer;
try {
  window.stg.setCamera(cam);
  window.stg.setTime(t);
  window.stg.snapshot().then(() => {
    const gl = r.gl, T = r.targets, values = new Float32Array(4 * T.width * T.height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, T.splatFbo);
    gl.readBuffer(gl.COLOR_ATTACHMENT0);
    gl.readPixels(0, 0, T.width, T.height, gl.RGBA, gl.FLOAT, values);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    const bytes = new Uint8Array(values.buffer);
    let text = "";
    for (let i = 0; i < bytes.length; i += 0x8000) text += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
    done({width: T.width, height: T.height, data: btoa(text)});
  }, (e) => done({error: String(e)}));
} catch (e) { done({error: String(e)}); }
"""


def splat_target(driver, camera: dict, t: float) -> np.ndarray:
    """(H, W, 4) float32, top row first: the first splat target (features 0..2 and alpha, before the
    colour pass) of window.stg.snapshot() after setCamera(camera) and setTime(t) (a lite model's
    splatted colour and alpha, to compare with Player.render_all's features and alpha)."""
    result = driver.execute_async_script(SPLAT_TARGET, camera, t)
    if "error" in result:
        raise AssertionError(f"reading the splat target failed: {result['error']}")
    data = np.frombuffer(base64.b64decode(result["data"]), np.float32)
    return data.reshape(result["height"], result["width"], 4)


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of uint8 `image` (H, W, 3) against float `reference` in [0, 1]."""
    mse = np.mean((image.astype(np.float64) / 255.0 - np.clip(reference, 0, 1).astype(np.float64)) ** 2)
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))
