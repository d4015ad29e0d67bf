"""stg-view in a real headless browser (Debian's chromium and chromium-driver, driven by selenium; .ci/run
installs them): the canvas shows the Player's render of the initial camera (training camera 0 at the
first frame), moving the time slider changes the picture as the Player's changes, and the server stops
cleanly on Ctrl-C. Set STG_VIEWER_SCREENSHOT=path.png to keep the first screenshot (docs/viewer.md's)."""
from __future__ import annotations

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")
pytest.importorskip("selenium")
CHROMIUM = shutil.which("chromium")
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="needs chromium and chromium-driver (apt)")

from stg_runtime import Player  # noqa: E402
from stg_runtime.viewer.camera import camera_from_viser, viser_pose  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "formats" / "vectors" / "full.stg"
WINDOW = (900, 600)
#: Columns of the canvas compared: clear of the notification (top left), the axes (bottom left) and
#: viser's panel (right).
COLUMNS = slice(330, 550)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255.0 ** 2
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def _interruptible() -> None:
    """In the child: Ctrl-C as in a terminal, whatever the test process inherited or blocked."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class ViewerProcess:
    """`stg-view MODEL --port P` in a subprocess, its stderr collected."""

    def __init__(self, port: int):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
        self.proc = subprocess.Popen([sys.executable, "-m", "stg_runtime.viewer.cli", str(MODEL), "--port", str(port),
                                      "--device", "cpu", "--jpeg-quality", "95"], cwd=ROOT, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     preexec_fn=_interruptible)
        self.err: list[str] = []
        threading.Thread(target=lambda: self.err.extend(self.proc.stderr), daemon=True).start()
        threading.Thread(target=lambda: self.proc.stdout.read(), daemon=True).start()

    def wait_serving(self, timeout: float = 120.0) -> None:
        end = time.monotonic() + timeout
        while not any("serving" in line for line in self.err):
            assert self.proc.poll() is None, "".join(self.err)
            assert time.monotonic() < end, "stg-view did not start: " + "".join(self.err)
            time.sleep(0.2)


@pytest.fixture(scope="module")
def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={WINDOW[0]},{WINDOW[1]}",
                "--force-device-scale-factor=1"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    yield driver
    driver.quit()


def canvas_image(driver) -> np.ndarray:
    """(H, W, 3) uint8 of the page's viewport, cropped to the canvas."""
    import imageio.v3 as iio
    width, height = driver.execute_script(
        "const c = Array.from(document.querySelectorAll('canvas')).pop(); return [c.clientWidth, c.clientHeight];")
    shot = iio.imread(io.BytesIO(driver.get_screenshot_as_png()))[..., :3]
    return shot[:height, :width]


def wait_for(driver, expected: np.ndarray, timeout: float = 120.0) -> tuple[float, np.ndarray]:
    """Screenshots until the compared columns reach 25 dB against `expected` (or the timeout): the last
    (PSNR, canvas image)."""
    end = time.monotonic() + timeout
    while True:
        image = canvas_image(driver)
        value = psnr(image[:, COLUMNS], expected[:, COLUMNS]) if image.shape == expected.shape else 0.0
        if value >= 25 or time.monotonic() > end:
            return value, image
        time.sleep(0.5)


def test_browser_shows_the_model_and_follows_the_time_slider(browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    player = Player(MODEL, device="cpu")
    times = player.frame_times()
    port = free_port()
    viewer = ViewerProcess(port)
    try:
        viewer.wait_serving()
        browser.get(f"http://127.0.0.1:{port}")
        time.sleep(2)
        width, height = canvas_image(browser).shape[1::-1]
        pose = viser_pose(player.cameras[0])
        camera = camera_from_viser(pose.wxyz, pose.position, pose.fov, width, height)  # training camera 0
        first = (np.clip(player.render(camera, times[0]), 0, 1) * 255 + 0.5).astype(np.uint8)
        last = (np.clip(player.render(camera, times[-1]), 0, 1) * 255 + 0.5).astype(np.uint8)
        assert psnr(first[:, COLUMNS], last[:, COLUMNS]) < 25  # the two times look different

        value, shown = wait_for(browser, first)
        if os.environ.get("STG_VIEWER_SCREENSHOT"):
            import imageio.v3 as iio
            iio.imwrite(os.environ["STG_VIEWER_SCREENSHOT"], canvas_image(browser))
        assert value >= 25, f"the canvas is {value:.1f} dB from the Player's render of camera 0 at the first frame"

        box = browser.find_elements(By.CSS_SELECTOR, "input[inputmode=decimal]")[0]  # the time slider's number
        box.send_keys(Keys.CONTROL, "a")
        box.send_keys(f"{times[-1]:.3f}", Keys.ENTER)
        value, moved = wait_for(browser, last)
        assert value >= 25, f"after moving the time slider the canvas is {value:.1f} dB from the Player's render"
        assert psnr(moved[:, COLUMNS], shown[:, COLUMNS]) < 25  # the picture changed
    finally:
        viewer.proc.send_signal(signal.SIGINT)
        try:
            code = viewer.proc.wait(timeout=90)  # (a busy machine can take long to stop the threads)
        except subprocess.TimeoutExpired:
            viewer.proc.kill()
            raise AssertionError("stg-view did not stop on Ctrl-C: " + "".join(viewer.err)) from None
    assert code == 0, "".join(viewer.err)
    assert "Traceback" not in "".join(viewer.err)
    with socket.socket() as s:  # the port is free again (nobody listens; TIME_WAIT may remain)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
