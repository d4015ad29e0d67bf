"""Colour on the CPU (formats/stg-v1.md, section 2): the full model's ONNX decoder run by onnxruntime,
and the lite colour. Splatted features (H, W, C) -> rgb (H, W, 3). The GPU's are in stg_runtime.cuda.decoder.
"""
from __future__ import annotations

import numpy as np
import onnxruntime as ort

from .camera import Camera
from .onnx_mlp import read_mlp

#: Clamp bounds as float32 scalars: np.clip of a float32 image with Python floats takes several times
#: as long (1.2 ms against 0.16 ms for a 640x360 rgb image, numpy 2.4).
_ZERO, _ONE = np.float32(0.0), np.float32(1.0)


def activate(x: np.ndarray, activation: str) -> np.ndarray:
    """The decoder's output activation, then clamped to [0, 1] for display."""
    if activation == "sigmoid":
        with np.errstate(over="ignore"):  # exp(-x) = inf for very negative x: sigmoid 0, as it should
            x = 1.0 / (1.0 + np.exp(-x))
    return np.clip(x, _ZERO, _ONE, out=x)


class OnnxDecoder:
    """Runs a segment's decoder with onnxruntime (on the CPU unless `providers` says otherwise).

    onnx_bytes: a decoder graph of formats/stg-v1.md (the MLP family, stg_runtime.onnx_mlp.read_mlp;
    ValueError otherwise), input (P, C + 3), output (P, 3), C the feature channel count; onnxruntime gets
    the graph re-serialised from its description, never these bytes. activation: "sigmoid", "clamp" or
    "identity". The input rows are [F[3:], camera centre, unit ray direction] (section 2).
    """

    def __init__(self, onnx_bytes: bytes, activation: str, threads: int = 0,
                 providers: tuple[str, ...] = ("CPUExecutionProvider",)):
        mlp = read_mlp(onnx_bytes)
        if mlp.output_width != 3:
            raise ValueError(f"decoder output must be (pixels, 3), got width {mlp.output_width}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.log_severity_level = 3
        # onnxruntime's idle threads otherwise spin after every run, taking the cores from the numba
        # splatter's next frame (docs/performance.md: "The decoder's idle threads")
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        options.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self.session = ort.InferenceSession(mlp.to_onnx(), options, providers=list(providers))
        self.input_name, self.input_channels = "x", mlp.input_width
        self.output_name = "y"
        self.activation = activation
        self._view_inputs: dict = {}  # per camera: (H*W, 6) [camera centre, ray direction], reused over time

    def view_inputs(self, camera: Camera) -> np.ndarray:
        """(H * W, 6) float32 [camera centre, unit ray direction] in world coordinates; cached."""
        key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
               camera.world_to_camera.tobytes(), camera.model, camera.distortion)
        cached = self._view_inputs.get(key)
        if cached is None:
            rays = camera.ray_directions().reshape(-1, 3)
            cached = np.empty((rays.shape[0], 6), np.float32)
            cached[:, :3] = camera.center
            cached[:, 3:] = rays
            if len(self._view_inputs) > 8:
                self._view_inputs.clear()
            self._view_inputs[key] = cached
        return cached

    def __call__(self, features: np.ndarray, camera: Camera) -> np.ndarray:
        """features (H, W, C) float32 splatted features -> rgb (H, W, 3) float32 in [0, 1]."""
        h, w, c = features.shape
        if c + 3 != self.input_channels:
            raise ValueError(f"decoder expects {self.input_channels - 3} feature channels, got {c}")
        flat = features.reshape(-1, c)
        x = np.empty((h * w, c + 3), np.float32)
        x[:, : c - 3] = flat[:, 3:]
        x[:, c - 3:] = self.view_inputs(camera)
        (y,) = self.session.run(None, {self.input_name: x})
        return activate(flat[:, :3] + y, self.activation).reshape(h, w, 3)


def lite_colour(features: np.ndarray) -> np.ndarray:
    """Lite models: rgb = clamp(F[..., 0:3], 0, 1)."""
    return np.clip(features[..., :3], _ZERO, _ONE)
