"""stg-render's outputs: H.264 mp4 that headless Chromium plays, gif and webm in their formats, sizes
rounded only with a note, and a camera path's frame k seen from camera k."""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import Player
from stg_runtime.camera import load_camera_path
from stg_runtime.cli import main as render_main
from stg_runtime.video import to_uint8

av = pytest.importorskip("av")
CHROMIUM = shutil.which("chromium")
DRIVER = shutil.which("chromedriver")


def decoded(path) -> tuple[str, str, int, int, int]:
    """(codec, pixel format, width, height, frame count) of a video file, read back with PyAV."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(video=0))
        ctx = stream.codec_context
        return ctx.name, ctx.pix_fmt, ctx.width, ctx.height, frames


def test_video_kinds_are_written_in_their_formats(inputs, tmp_path, capsys):
    base = [inputs["model"], "--quiet", "--end", "0.1"]  # the model's 4 frames
    assert render_main(base + ["--out", str(tmp_path / "v.mp4"), "--size", "161x121"]) == 0
    note = capsys.readouterr().err
    assert "161x121" in note and "160x120" in note and note.startswith("stg-render: note:")  # rounded, said so
    assert decoded(tmp_path / "v.mp4") == ("h264", "yuv420p", 160, 120, 4)
    assert render_main(base + ["--out", str(tmp_path / "v.webm"), "--size", "64x48"]) == 0
    assert decoded(tmp_path / "v.webm")[0] == "vp9" and decoded(tmp_path / "v.webm")[2:] == (64, 48, 4)
    assert render_main(base + ["--out", str(tmp_path / "v.gif"), "--size", "33x25"]) == 0
    assert (tmp_path / "v.gif").read_bytes()[:6] == b"GIF89a"
    assert decoded(tmp_path / "v.gif")[2:] == (33, 25, 4)  # gif keeps odd sizes
    assert capsys.readouterr().err == ""
    assert not (tmp_path / "v.gif").is_dir() and not (tmp_path / "v.webm").is_dir()
    assert render_main(base + ["--out", str(tmp_path / "v.avi")]) == 2
    assert not (tmp_path / "v.avi").exists()


def test_frame_k_of_a_camera_path_is_seen_from_camera_k(inputs, tmp_path):
    import cv2

    assert render_main([inputs["model"], "--path", inputs["path"], "--out", str(tmp_path / "frames"), "--quiet"]) == 0
    player = Player(inputs["model"], device="cpu")
    cameras = load_camera_path(inputs["path"])
    files = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert len(files) == len(cameras) == 4
    for k, (file, times) in enumerate(zip(files, player.frame_times())):
        image = cv2.imread(str(file))[..., ::-1]
        expected = [to_uint8(player.render(cam, float(times))) for cam in cameras]
        assert np.array_equal(image, expected[k])
        assert all(not np.array_equal(image, e) for j, e in enumerate(expected) if j != k)  # the cameras differ


def _plays(driver, video: Path) -> dict:
    """Load `video` in a <video> element of a local page and play it: what the page saw."""
    page = video.with_suffix(".html")
    page.write_text(f'<!doctype html><video src="{video.name}" muted playsinline></video>')
    driver.get(page.as_uri())
    return driver.execute_async_script("""
        const done = arguments[arguments.length - 1];
        const v = document.querySelector('video');
        const report = () => done({width: v.videoWidth, height: v.videoHeight, time: v.currentTime,
                                   error: v.error ? v.error.code + ' ' + v.error.message : null});
        v.addEventListener('error', report);
        v.addEventListener('timeupdate', () => { if (v.currentTime > 0) report(); });
        v.play().catch(report);
        setTimeout(report, 20000);
    """)


@pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="needs chromium and chromium-driver (apt)")
def test_the_mp4_plays_in_headless_chromium(inputs, tmp_path):
    pytest.importorskip("selenium")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    assert render_main([inputs["model"], "--out", str(tmp_path / "v.mp4"), "--size", "64x48", "--fps", "10",
                        "--quiet"]) == 0
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--autoplay-policy=no-user-gesture-required",
                f"--user-data-dir={tempfile.mkdtemp(prefix='chromium-')}"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    driver.set_script_timeout(60)
    try:
        seen = _plays(driver, tmp_path / "v.mp4")
        assert seen["error"] is None and (seen["width"], seen["height"]) == (64, 48) and seen["time"] > 0, seen
        try:  # the check can fail: the MPEG-4 Part 2 (mp4v) video stg-render once wrote does not play
            import cv2
        except ImportError:
            return
        writer = cv2.VideoWriter(str(tmp_path / "old.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (64, 48))
        for _ in range(10):
            writer.write(np.zeros((48, 64, 3), np.uint8))
        writer.release()
        seen = _plays(driver, tmp_path / "old.mp4")
        assert seen["error"] is not None or seen["width"] == 0, seen
    finally:
        driver.quit()
