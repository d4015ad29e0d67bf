"""`Player`: open a `.stg` model and render it from any camera at any time."""
from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from . import format as stg_format
from .camera import Camera, load_camera_path
from .decoder import OnnxDecoder, lite_colour
from .model import Model, Segment
from .progress import Progress
from .sh import sh_colours
from .splat_cpu import rasterize
from .timeeval import evaluate
from .video import FrameWriter

DEVICES = ("cpu", "cuda", "auto")


class RenderError(RuntimeError):
    """Rendering a loaded model failed (onnxruntime, memory, a non-finite image, ...); the message starts
    with the model's file name (or "<model>") and says at what time and why."""


class Rendered(NamedTuple):
    """One render: rgb (H, W, 3) in [0, 1]; features (H, W, C) splatted (for "sh" models the splatted
    per-Gaussian colours, C = 3); alpha (H, W); depth (H, W)
    expected depth along the camera's z axis (0 where alpha is 0). All float32."""

    rgb: np.ndarray
    features: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray


def _resolve_device(device: str) -> str:
    """"cpu", or "cuda" (numba.cuda kernels: a real GPU, or numba's simulator when NUMBA_ENABLE_CUDASIM=1);
    "auto" is "cuda" only when numba sees a real GPU, never the simulator."""
    if device not in DEVICES:
        raise ValueError(f"device must be one of {DEVICES}, got {device!r}")
    if device == "cpu":
        return "cpu"
    from .cuda import device as cuda_device  # numba.cuda is imported only when a GPU is asked about
    if device == "cuda":
        cuda_device.require()
        return "cuda"
    return "cuda" if cuda_device.gpu_available() else "cpu"


class Player:
    """Plays a Spacetime Gaussian model.

    source: path of a `.stg` file (read with stg_runtime.format.load and `limits`: FormatError for a bad
    file), or a `Model`. device: "cpu", "cuda" (numba.cuda kernels, see stg_runtime.cuda; RuntimeError
    when numba sees no GPU) or "auto" ("cuda" when numba sees a GPU, else "cpu"). Times are in seconds
    of the video (frame k is shown at k / fps). A render that fails raises RenderError; bad arguments
    (a time outside the model's span, say) raise ValueError.
    """

    def __init__(self, source: str | Path | Model, device: str = "auto",
                 limits: stg_format.Limits = stg_format.DEFAULT_LIMITS):
        self.device = _resolve_device(device)
        self.model = source if isinstance(source, Model) else stg_format.load(source, limits)
        self.name = "<model>" if isinstance(source, Model) else os.fsdecode(source)
        self._decoders: dict[int, OnnxDecoder] = {}
        self._device_decoders: dict[int, object] = {}  # device "cuda": per segment, Fused/OnnxDeviceDecoder
        self._device_segments: dict[int, object] = {}  # device "cuda": per segment, its DeviceSegment
        self._workspace = None  # device "cuda": cuda.memory.Workspace, the buffers kept between frames

    # -- what the model covers -----------------------------------------------------------------
    @property
    def kind(self) -> str:
        return self.model.kind

    @property
    def fps(self) -> float:
        return self.model.fps

    @property
    def num_frames(self) -> int:
        return self.model.num_frames

    @property
    def start_time(self) -> float:
        """Seconds at which the model's first frame is shown (0 unless it starts mid-video)."""
        return self.model.start_frame / self.model.fps

    @property
    def duration(self) -> float:
        """Seconds covered by the model."""
        return self.model.duration

    @property
    def cameras(self) -> list[Camera]:
        """The cameras the model was trained with."""
        return list(self.model.cameras)

    def frame_times(self) -> np.ndarray:
        """(num_frames,) seconds at which each frame of the model is shown."""
        return (self.model.start_frame + np.arange(self.num_frames)) / self.fps

    # -- rendering -------------------------------------------------------------------------------
    def render(self, camera: Camera, t: float, out: str = "host") -> np.ndarray:
        """(H, W, 3) float32 rgb in [0, 1] seen by `camera` at time `t` seconds. out="device" (device
        "cuda" only) returns it as a numba device array, left on the GPU: one of the player's own
        buffers, which its next render overwrites (copy it to keep it)."""
        return self.render_all(camera, t, out=out).rgb

    def render_frame(self, camera: Camera, frame: int) -> np.ndarray:
        """Like render, at the time of frame index `frame` of the video."""
        return self.render(camera, frame / self.fps)

    def render_all(self, camera: Camera, t: float, out: str = "host") -> Rendered:
        """rgb plus the splatted features, alpha and depth (with out="device": numba device arrays, the
        player's buffers, overwritten by its next render)."""
        if out not in ("host", "device"):
            raise ValueError(f"out must be 'host' or 'device', got {out!r}")
        if out == "device" and self.device != "cuda":
            raise ValueError(f"out='device' needs device 'cuda', this player renders on {self.device!r}")
        end = self.start_time + self.duration
        if not (self.start_time - 1e-9 <= t <= end + 1e-9):
            raise ValueError(f"t = {t} s is outside the model's time span [{self.start_time}, {end}] s")
        parts = self.model.segments_at(t)
        try:
            if len(parts) == 1:
                rendered = self._render(parts[0][0], parts[0][1], camera, out)
            else:
                rendered = self._crossfade(parts, camera, out)
        except Exception as e:  # noqa: BLE001 - any failure of a render is reported as one, naming the file
            raise RenderError(f"{self.name}: rendering t = {t} s failed ({type(e).__name__}: {e})") from e
        if out == "host" and not np.all(np.isfinite(rendered.rgb)):
            raise RenderError(f"{self.name}: the image at t = {t} s has non-finite values")
        return rendered

    def _render(self, segment: Segment, tau: float, camera: Camera, out: str) -> Rendered:
        """render_all's work on the CPU (numba splatter, onnxruntime decoder) or the GPU."""
        if self.device == "cuda":
            return self._render_cuda(segment, tau, camera, out)
        g = evaluate(segment, tau)
        splatted = g.features
        if self.model.kind == "sh":  # colour per Gaussian for this view, before splatting (as 3DGS does)
            splatted = sh_colours(g.features, g.means, camera.center)
        features, alpha, depth = rasterize(g.means, g.quats, g.scales, g.opacities, splatted, camera)
        if self.model.kind in ("lite", "sh"):
            rgb = lite_colour(features)
        else:
            rgb = self._decoder(segment)(features, camera)
        return Rendered(np.ascontiguousarray(rgb, dtype=np.float32), features, alpha, depth)

    def _crossfade(self, parts, camera: Camera, out: str) -> Rendered:
        """Inside a crossfade (Model.segments_at): each of rgb, features, alpha and depth is the weighted
        sum of the two segments' renders (on the host; with out="device" the sums are copied into the
        player's buffers)."""
        (a_seg, a_tau, a_w), (b_seg, b_tau, b_w) = parts
        first = self._render(a_seg, a_tau, camera, "host")
        second = self._render(b_seg, b_tau, camera, "host")
        blended = Rendered(*(np.ascontiguousarray(a_w * x + b_w * y, dtype=np.float32)
                             for x, y in zip(first, second)))
        if out == "host":
            return blended
        ws = self._workspace
        buffers = [ws.buffer(f"crossfade {name}", a.shape, np.float32).device
                   for name, a in zip(Rendered._fields, blended)]
        for buffer, host in zip(buffers, blended):
            buffer.copy_to_device(host)
        return Rendered(*buffers)

    def _render_cuda(self, segment: Segment, tau: float, camera: Camera, out: str) -> Rendered:
        """Time evaluation, splatting and colour with the numba.cuda kernels, on segments uploaded once.
        The colour of full models is the fused decoder, except for decoder graphs other than
        12 -> 6 -> 3 MatMul/Relu (cuda.decoder.OnnxDeviceDecoder: onnxruntime). "sh" models get their
        per-Gaussian colours for this view on the device (cuda.decoder.sh_colours) before splatting."""
        from .cuda import decoder as decoder_cuda
        from .cuda import splat as splat_cuda
        from .cuda.memory import Workspace
        from .cuda.timeeval import DeviceSegment
        key = id(segment)
        if key not in self._device_segments:
            self._device_segments[key] = DeviceSegment(segment)
        if self._workspace is None:
            self._workspace = Workspace()
        ws = self._workspace
        gaussians = self._device_segments[key].evaluate(tau)
        if self.model.kind == "sh":
            means, coeffs = gaussians[0], gaussians[4]
            colours = ws.buffer("sh colours", (means.shape[0], 3), np.float32).device
            gaussians = (*gaussians[:4], decoder_cuda.sh_colours(coeffs, means, camera, out=colours))
        features, alpha, depth = splat_cuda.rasterize(*gaussians, camera, out="device", workspace=ws)
        rgb_out = ws.buffer("rgb", (camera.height, camera.width, 3), np.float32).device
        if self.model.kind in ("lite", "sh"):
            rgb = decoder_cuda.lite_colour(features, out=rgb_out)
        else:
            if key not in self._device_decoders:
                self._device_decoders[key] = (decoder_cuda.FusedDecoder.from_onnx(segment.decoder, segment.activation)
                                              or decoder_cuda.OnnxDeviceDecoder(segment.decoder, segment.activation))
            rgb = self._device_decoders[key](features, camera, out=rgb_out)
        if out == "device":
            return Rendered(rgb, features, alpha, depth)
        host = lambda a: a if isinstance(a, np.ndarray) else a.copy_to_host()  # noqa: E731
        return Rendered(host(rgb), host(features), host(alpha), host(depth))

    def _decoder(self, segment: Segment) -> OnnxDecoder:
        key = id(segment)
        if key not in self._decoders:
            self._decoders[key] = OnnxDecoder(segment.decoder, segment.activation)
        return self._decoders[key]

    def render_video(self, path, cameras: Camera | Sequence[Camera] | str | Path, times=None,
                     fps: float | None = None, progress: bool = True) -> int:
        """Render a video (.mp4, .mov, .mkv: H.264; .webm; .gif; through PyAV, stg_runtime.video) or a
        folder of PNG frames; returns the frame count.

        cameras: one Camera (fixed view), one Camera per output frame, or the path of a camera-path JSON
        file (a list of camera objects as in formats/stg-v1.md). times: seconds of each output frame
        (default: every frame of the model). fps: of the output file (default: the model's).
        """
        if isinstance(cameras, (str, Path)):
            cameras = load_camera_path(cameras)
        if isinstance(cameras, Camera):
            cameras = [cameras]
        cameras = list(cameras)
        times = self.frame_times() if times is None else np.asarray(times, dtype=np.float64)
        if len(cameras) == 1:
            cameras = cameras * len(times)
        if len(cameras) != len(times):
            raise ValueError(f"{len(cameras)} cameras for {len(times)} frames: give one camera, or one per frame")
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) != 1:
            raise ValueError(f"all cameras of a video must have one image size, got {sorted(sizes)}")
        (width, height), = sizes
        writer = FrameWriter(path, fps or self.fps, width, height)
        ok = False
        try:
            for camera, t in Progress(list(zip(cameras, times)), desc="render", enabled=progress):
                writer.write(self.render(camera, float(t)))
            ok = True
        finally:
            writer.close(ok)
        return writer.count
