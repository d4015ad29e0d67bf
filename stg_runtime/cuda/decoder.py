"""Colour on the GPU (numba.cuda): the decoder of formats/stg-v1.md, section 2, applied to a splatted
feature image that stays on the device.

    sh_colours(coeffs_d, means_d, camera) -> rgb_d   "sh" models, per Gaussian before splatting:
                                                      (M, 3 K) SH coefficients -> (M, 3) colours
    lite_colour(features_d) -> rgb_d                  lite and "sh" models: clamp(F[..., :3], 0, 1)
    FusedDecoder.from_onnx(onnx, activation)          the 12 -> 6 -> 3 MatMul/Relu graph, one thread
        (features_d, camera) -> rgb_d                 per pixel, weights read out of the graph
    OnnxDeviceDecoder(onnx, activation)               any decoder graph the format allows, run by
        (features_d, camera) -> rgb_d                 onnxruntime: its CUDA provider where installed

features_d: (H, W, C) float32 device array; rgb_d: (H, W, 3) float32 device array in [0, 1]; each also
takes out=, a device array to write the result into (Player passes its workspace's). The
fused decoder is the fast path; OnnxDeviceDecoder is its reference and runs the graphs it cannot fuse.
OnnxDeviceDecoder builds the decoder's input rows [F[3:], camera centre, ray] on the device; with
onnxruntime's CUDAExecutionProvider (the onnxruntime-gpu package) and a real GPU it binds those device
buffers to the session (IOBinding), so nothing leaves the GPU; otherwise the rows are copied to the host,
run on the CPU provider and the result copied back.
"""
from __future__ import annotations

import math

import numpy as np
from numba import cuda

from ..camera import Camera
from ..decoder import OnnxDecoder
from ..model import sh_degree_of
from ..onnx_mlp import read_mlp
from ..projection import camera_params, pixel_ray
from ..sh import sh_colour_at
from .device import simulated
from .launch import launch
from .memory import device_empty
from .minmax import dmax, dmin

CUDA_PROVIDER = "CUDAExecutionProvider"


def _grid2d(W, H, block=16):
    return (-(-W // block), -(-H // block)), (block, block)


_pixel_ray = cuda.jit(device=True, inline=True)(pixel_ray)


@cuda.jit(device=True)
def _ray(cam, ix, iy):
    """The unit world-space ray through pixel centre (ix, iy) (3 float64; cam as
    projection.camera_params; projection.pixel_ray)."""
    return _pixel_ray(cam, ix + 0.5, iy + 0.5)


@cuda.jit
def _decode(features, w1, w2, cam, sigmoid, rgb):
    """One thread per pixel: rgb = act(F[:3] + W2 relu(W1 [F[3:], centre, ray])), clamped to [0, 1]."""
    ix, iy = cuda.grid(2)
    if iy >= rgb.shape[0] or ix >= rgb.shape[1]:
        return
    x = cuda.local.array(12, np.float32)
    for c in range(6):
        x[c] = features[iy, ix, 3 + c]
    x[6], x[7], x[8] = cam[16], cam[17], cam[18]
    x[9], x[10], x[11] = _ray(cam, ix, iy)
    h = cuda.local.array(6, np.float32)
    for j in range(6):
        s = np.float32(0.0)
        for c in range(12):
            s += w1[j, c] * x[c]
        h[j] = dmax(s, np.float32(0.0))
    for j in range(3):
        s = np.float32(0.0)
        for c in range(6):
            s += w2[j, c] * h[c]
        s += features[iy, ix, j]
        if sigmoid:
            s = np.float32(1.0) / (np.float32(1.0) + math.exp(-s))
        rgb[iy, ix, j] = dmin(dmax(s, np.float32(0.0)), np.float32(1.0))


@cuda.jit
def _decoder_rows(features, cam, rows):
    """rows[p] = [F[p, 3:], centre, ray] (p = iy * W + ix), the ONNX decoder's input, float32."""
    ix, iy = cuda.grid(2)
    H, W, C = features.shape
    if iy >= H or ix >= W:
        return
    p = iy * W + ix
    for c in range(3, C):
        rows[p, c - 3] = features[iy, ix, c]
    rows[p, C - 3], rows[p, C - 2], rows[p, C - 1] = cam[16], cam[17], cam[18]
    rows[p, C], rows[p, C + 1], rows[p, C + 2] = _ray(cam, ix, iy)


@cuda.jit
def _add_base(features, y, sigmoid, rgb):
    """rgb = act(F[:3] + y), clamped to [0, 1]; y (H * W, 3) the decoder's output."""
    ix, iy = cuda.grid(2)
    if iy >= rgb.shape[0] or ix >= rgb.shape[1]:
        return
    p = iy * rgb.shape[1] + ix
    for j in range(3):
        s = features[iy, ix, j] + y[p, j]
        if sigmoid:
            s = np.float32(1.0) / (np.float32(1.0) + math.exp(-s))
        rgb[iy, ix, j] = dmin(dmax(s, np.float32(0.0)), np.float32(1.0))


@cuda.jit
def _lite(features, rgb):
    ix, iy = cuda.grid(2)
    if iy < rgb.shape[0] and ix < rgb.shape[1]:
        for j in range(3):
            rgb[iy, ix, j] = dmin(dmax(features[iy, ix, j], np.float32(0.0)), np.float32(1.0))


def _out(out, shape):
    """`out` if given (checked), else a new float32 device array of `shape`."""
    if out is None:
        return device_empty(shape, np.float32)
    if tuple(out.shape) != shape or out.dtype != np.float32:
        raise ValueError(f"out must be a float32 device array of shape {shape}, got {out.dtype} {tuple(out.shape)}")
    return out


def lite_colour(features_d, out=None):
    """Device (H, W, C) features -> device (H, W, 3) rgb = clamp(F[..., :3], 0, 1)."""
    H, W = features_d.shape[:2]
    rgb = _out(out, (H, W, 3))
    launch(_lite, *_grid2d(W, H), features_d, rgb)
    return rgb


_sh_colour_at = cuda.jit(device=True, inline=True)(sh_colour_at)


@cuda.jit
def _sh(coeffs, means, cam, out):
    """One thread per Gaussian: stg_runtime.sh.sh_colour_at from the camera centre cam[16:19]."""
    i = cuda.grid(1)
    if i < coeffs.shape[0]:
        _sh_colour_at(coeffs, means, cam[16], cam[17], cam[18], i, out)


def sh_colours(coeffs_d, means_d, camera: Camera, out=None):
    """Device (M, 3 K) SH coefficients (K = 1, 4, 9 or 16; layout of stg_runtime.sh) and (M, 3) means,
    seen from `camera` -> device (M, 3) float32 colours, as stg_runtime.sh.sh_colours."""
    sh_degree_of(coeffs_d.shape[1])
    m = coeffs_d.shape[0]
    out = _out(out, (m, 3))
    if m:
        launch(_sh, -(-m // 256), 256, coeffs_d, means_d, camera_params(camera), out)
    return out


class FusedDecoder:
    """The full model's decoder on the device: weights [W1 (6, 12), W2 (3, 6)] of a bias-free
    onnx_mlp.MLP (the format's reference 12 -> 6 -> 3 graph), activation "sigmoid", "clamp"
    or "identity" (the last two: clamped to [0, 1] only)."""

    def __init__(self, weights, activation: str):
        if (len(weights) != 2 or tuple(weights[0].shape) != (6, 12) or tuple(weights[1].shape) != (3, 6)):
            raise ValueError("the fused decoder needs the 12 -> 6 -> 3 MatMul/Relu graph, got layers "
                             f"{[tuple(w.shape) for w in weights]}")
        self.w1 = cuda.to_device(np.ascontiguousarray(weights[0], np.float32))
        self.w2 = cuda.to_device(np.ascontiguousarray(weights[1], np.float32))
        self.sigmoid = activation == "sigmoid"

    @classmethod
    def from_onnx(cls, onnx_bytes: bytes, activation: str):
        """A FusedDecoder, or None if the decoder is not the bias-free 12 -> 6 -> 3 MLP (ValueError for
        bytes that are no valid decoder)."""
        mlp = read_mlp(onnx_bytes)
        shapes = [w.shape for w in mlp.weights]
        if shapes != [(6, 12), (3, 6)] or any(b is not None for b in mlp.biases):
            return None
        return cls(list(mlp.weights), activation)

    def __call__(self, features_d, camera: Camera, out=None):
        """Device (H, W, 9) features -> device (H, W, 3) rgb in [0, 1]."""
        H, W, C = features_d.shape
        if C != 9:
            raise ValueError(f"the fused decoder expects 9 feature channels, got {C}")
        rgb = _out(out, (H, W, 3))
        launch(_decode, *_grid2d(W, H), features_d, self.w1, self.w2, camera_params(camera), self.sigmoid, rgb)
        return rgb


def cuda_provider_available() -> bool:
    """Whether onnxruntime offers its CUDA provider (onnxruntime-gpu) and numba sees a real GPU."""
    import onnxruntime as ort
    return not simulated() and CUDA_PROVIDER in ort.get_available_providers()


def _preload_cuda_libraries() -> None:
    """Let onnxruntime-gpu find the CUDA and cuDNN libraries of pip's nvidia-* packages (its extras
    [cuda,cudnn]), which are not on the loader's path: onnxruntime.preload_dlls (onnxruntime >= 1.21)
    loads them once. Without them its CUDA provider fails to load and the session runs on the CPU."""
    import onnxruntime as ort
    if not _PRELOADED and hasattr(ort, "preload_dlls"):
        _PRELOADED.append(True)
        try:
            ort.preload_dlls()
        except Exception:  # noqa: BLE001 (no such packages: the libraries may still be on the path)
            pass


_PRELOADED: list = []


def run_bound(decoder: OnnxDecoder, device_type: str, rows_ptr: int, rows: int, out_ptr: int) -> None:
    """Run `decoder`'s session on buffers it does not own (onnxruntime IOBinding): float32 input
    (rows, channels) at address rows_ptr, float32 output (rows, 3) written at out_ptr; device_type
    "cuda" (device 0) or "cpu". The caller keeps both buffers alive and, for "cuda", synchronised."""
    binding = decoder.session.io_binding()
    binding.bind_input(decoder.input_name, device_type, 0, np.float32, [rows, decoder.input_channels], rows_ptr)
    binding.bind_output(decoder.output_name, device_type, 0, np.float32, [rows, 3], out_ptr)
    decoder.session.run_with_iobinding(binding)


class OnnxDeviceDecoder:
    """A segment's ONNX decoder (any graph the format allows) applied to a device feature image.

    With onnxruntime's CUDA provider (see cuda_provider_available) the session runs on the GPU on the
    device buffers themselves; otherwise on the CPU provider, through one copy each way.
    """

    def __init__(self, onnx_bytes: bytes, activation: str):
        self.on_device = cuda_provider_available()
        if self.on_device:
            _preload_cuda_libraries()
        # TF32 off: onnxruntime's CUDA provider multiplies float32 matrices in TF32 by default (errors
        # near 1e-3, seen on an H100), the CPU decoder in float32.
        providers = (((CUDA_PROVIDER, {"use_tf32": "0"}), "CPUExecutionProvider") if self.on_device
                     else ("CPUExecutionProvider",))
        self.decoder = OnnxDecoder(onnx_bytes, activation, providers=providers)
        # onnxruntime falls back to the CPU when the CUDA provider cannot load (missing CUDA libraries).
        self.on_device = CUDA_PROVIDER in self.decoder.session.get_providers()
        self.sigmoid = activation == "sigmoid"

    def __call__(self, features_d, camera: Camera, out=None):
        """Device (H, W, C) features -> device (H, W, 3) rgb in [0, 1]."""
        H, W, C = features_d.shape
        if C + 3 != self.decoder.input_channels:
            raise ValueError(f"decoder expects {self.decoder.input_channels - 3} feature channels, got {C}")
        grid = _grid2d(W, H)
        rows = device_empty((H * W, C + 3), np.float32)
        _decoder_rows[grid](features_d, camera_params(camera), rows)
        if self.on_device:
            y = device_empty((H * W, 3), np.float32)
            cuda.synchronize()  # onnxruntime runs on a stream of its own
            run_bound(self.decoder, "cuda", rows.__cuda_array_interface__["data"][0], H * W,
                      y.__cuda_array_interface__["data"][0])
        else:
            (y,) = self.decoder.session.run(None, {self.decoder.input_name: rows.copy_to_host()})
            y = cuda.to_device(np.ascontiguousarray(y, np.float32))
        rgb = _out(out, (H, W, 3))
        _add_base[grid](features_d, y, self.sigmoid, rgb)
        return rgb
