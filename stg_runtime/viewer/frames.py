"""The viewer's render callback: a browser's view, a time and a render mode -> the image sent to it.

`render_image` is what a browser is sent: the Player's render for that camera and time, as 8-bit
rgb. `ClientStream` renders for one connected browser whenever its camera, the time, the mode or the
model changes: at a preview size while the camera moves, at full size once it rests. It reads a
client the way viser presents one (`client.camera.wxyz / position / fov / image_width / image_height`,
`client.scene.set_background_image`), without importing viser. `RenderThread` runs the renders of
every browser, one at a time, on one thread.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..decoder import activate
from ..video import to_uint8
from .camera import camera_from_viser, scaled

MODES = ("rgb", "depth", "alpha", "base colour")
#: Seconds after the last camera change during which the camera counts as moving (preview size).
SETTLE_SECONDS = 0.25


def modes_for(kind: str) -> tuple[str, ...]:
    """The render modes of a model kind: base colour (the splatted F[0:3] without the decoder) only
    for full models."""
    return MODES if kind == "full" else MODES[:3]


def depth_image(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(H, W) expected depth -> (H, W, 3) float grey in [0, 1]: near is bright, far dark, over the
    2nd..98th percentile of the covered pixels (alpha > 0.5); uncovered pixels are black."""
    covered = alpha > 0.5
    if not covered.any():
        return np.zeros((*depth.shape, 3), np.float32)
    near, far = np.percentile(depth[covered], [2, 98])
    grey = 1.0 - (depth - near) / max(far - near, 1e-9)
    grey = np.where(covered, np.clip(grey, 0.05, 1.0), 0.0).astype(np.float32)
    return np.repeat(grey[..., None], 3, axis=2)


def render_image(player, camera: Camera, t: float, mode: str = "rgb") -> np.ndarray:
    """(H, W, 3) uint8 of `player` seen by `camera` at `t` seconds: mode "rgb" is Player.render, "depth"
    and "alpha" grey images (depth_image), "base colour" the full model's splatted F[0:3] through its
    output activation, without the decoder."""
    if mode == "rgb":
        return to_uint8(player.render(camera, t))
    if mode not in MODES:
        raise ValueError(f"render mode must be one of {MODES}, got {mode!r}")
    r = player.render_all(camera, t)
    if mode == "depth":
        image = depth_image(r.depth, r.alpha)
    elif mode == "alpha":
        image = np.repeat(r.alpha[..., None], 3, axis=2)
    elif player.kind == "full":
        segment, _ = player.model.segment_at(t)
        image = activate(np.array(r.features[..., :3], dtype=np.float32), segment.activation)
    else:
        image = r.rgb
    return to_uint8(image)


@dataclass
class ViewSettings:
    """What every browser is shown: the render mode, the largest image (pixels) at rest and while the
    camera moves, and the JPEG quality of the stream."""

    mode: str = "rgb"
    max_pixels: int = 1280 * 720
    preview_pixels: int = 320 * 180
    jpeg_quality: int = 90


@dataclass
class FrameStats:
    """The last frame sent to a browser: its camera, time, mode, whether a preview, render seconds
    (the Player's render, and any wait for other browsers' renders) and the wall-clock time it was
    sent; `sent` counts frames, `render_total` adds up their render seconds."""

    camera: Camera | None = None
    t: float = 0.0
    mode: str = "rgb"
    preview: bool = False
    render_seconds: float = 0.0
    sent_at: float = 0.0
    sent: int = 0
    render_total: float = 0.0
    intervals: list = field(default_factory=list)  # seconds between the last frames sent (up to 30)


def client_camera(client) -> tuple[tuple, Camera] | None:
    """(a hashable key of the view, our Camera at the canvas size) for a viser client, or None before
    the browser has reported its camera and canvas."""
    cam = client.camera
    try:
        width, height = int(cam.image_width), int(cam.image_height)
        wxyz, position, fov = np.asarray(cam.wxyz, float), np.asarray(cam.position, float), float(cam.fov)
    except AssertionError:  # viser asserts until the first camera message arrives
        return None
    if width <= 0 or height <= 0 or not fov > 0 or not np.all(np.isfinite(wxyz)) or not wxyz.any():
        return None
    key = (tuple(wxyz), tuple(position), fov, width, height)
    return key, camera_from_viser(wxyz, position, fov, width, height)


class RenderThread:
    """Runs functions (renders) one at a time on one long-lived thread: `run(fn, *args)` returns
    fn(*args), or raises what it raised.

    Why one thread: numba's OpenMP threading layer keeps a pool of worker threads for every thread
    that starts parallel work, and renders started from several threads at once (one per browser)
    were each several times slower than from one (docs/viewer.md). Rendering for every browser on one
    thread keeps one pool."""

    def __init__(self):
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stg-view render")

    def run(self, fn, *args):
        return self._executor.submit(fn, *args).result()

    def close(self) -> None:
        """Stop the thread once the render in progress is done; later calls to run raise RuntimeError."""
        self._executor.shutdown(wait=False, cancel_futures=True)


class ClientStream:
    """Renders for one browser. `render_once()` renders and sends one frame when anything changed since
    the last (camera, time, mode, model), or the full-size frame once the camera rests after a preview;
    it returns whether it sent one. `run()` loops over render_once until `stop()`.

    source(): the current (Player, model version, time in seconds); settings: a ViewSettings;
    renderer: the RenderThread that renders (shared by the streams of a viewer), or None to render on
    the calling thread."""

    def __init__(self, client, source, settings: ViewSettings, renderer: RenderThread | None = None):
        self.client, self.source, self.settings = client, source, settings
        self.render = renderer.run if renderer is not None else (lambda fn, *args: fn(*args))
        self.stats = FrameStats()
        self._last_key = None
        self._camera_key = None
        self._camera_changed = 0.0
        self._stopped = threading.Event()
        self._wake = threading.Event()

    def wake(self) -> None:
        """Check for a change now (rather than at the next poll)."""
        self._wake.set()

    def stop(self) -> None:
        self._stopped.set()
        self._wake.set()

    def render_once(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        view = client_camera(self.client)
        if view is None:
            return False
        camera_key, camera = view
        if camera_key != self._camera_key:
            self._camera_key, self._camera_changed = camera_key, now
        player, version, t = self.source()
        preview = now - self._camera_changed < SETTLE_SECONDS and self._last_key is not None
        key = (camera_key, t, self.settings.mode, version)
        if key == self._last_key and (preview or not self.stats.preview):
            return False
        size = self.settings.preview_pixels if preview else self.settings.max_pixels
        camera = scaled(camera, size)
        start = time.perf_counter()
        image = self.render(render_image, player, camera, t, self.settings.mode)
        seconds = time.perf_counter() - start
        if self._stopped.is_set():  # the browser left (or the server stops) while this frame rendered
            return False
        self.client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.settings.jpeg_quality)
        self._last_key = key
        sent_at = time.monotonic()
        s = self.stats
        if s.sent:
            s.intervals = (s.intervals + [sent_at - s.sent_at])[-30:]
        s.camera, s.t, s.mode, s.preview, s.render_seconds, s.sent_at = camera, t, self.settings.mode, preview, seconds, sent_at
        s.sent += 1
        s.render_total += seconds
        return True

    def run(self, poll_seconds: float = 0.01, on_error=None) -> None:
        """Render on every change until stop(); on_error(exception) is told of a failed frame (the
        stream goes on with the next change)."""
        while not self._stopped.is_set():
            try:
                sent = self.render_once()
            except Exception as e:  # noqa: BLE001 - a failed frame must not end the stream
                if self._stopped.is_set():  # the viewer closed (and its RenderThread) under this frame
                    break
                self._last_key = None
                sent = False
                if on_error is not None:
                    on_error(e)
                self._stopped.wait(0.5)
            if not sent:
                self._wake.wait(poll_seconds)
                self._wake.clear()
