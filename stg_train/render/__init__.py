"""Differentiable rendering for training: one `rasterize`, two backends.

    rasterize(means, quats, scales, opacities, features, camera, backend="torch") -> RenderOutput

    resolve_backend(name, device) -> "numba", "torch" or "gsplat"

Backends: "numba" (stg_train.render.numba_splat, the CPU training splatter: numba kernels with a
backward pass), "torch" (stg_train.render.torch_splat, the readable reference, any device) and "gsplat"
(stg_train.render.gsplat_backend, gsplat's CUDA kernels). numba and gsplat are imported only when used.
All follow formats/stg-v1.md, section 3, and return the same RenderOutput. Cameras may be pinhole or
fisheye (stg_runtime Camera.model): torch and numba draw both; gsplat draws pinholes and equidistant
fisheyes and hands a fisheye with k1..k4 to the torch splatter (gsplat_backend's docstring says why;
docs/training.md, "Camera models"). The backends are registered in stg_train.choices.SPLATTERS
(name -> "module:function"), each module imported when its backend first draws; docs/extending.md adds one.
"""
from __future__ import annotations

import importlib

from torch import Tensor

from ..choices import SPLATTERS
from .output import RenderOutput

__all__ = ["BACKENDS", "RenderOutput", "rasterize", "resolve_backend"]


def __getattr__(name: str):
    """BACKENDS: the backends' names, as stg_train.choices.SPLATTERS holds them now."""
    if name == "BACKENDS":
        return tuple(SPLATTERS)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor, camera,
              *, backend: str = "torch", **options) -> RenderOutput:
    """Render M Gaussians (means (M, 3) world, quats (M, 4) wxyz, scales (M, 3) standard deviations,
    opacities (M,) or (M, 1), features (M, C); one device and float dtype) seen by `camera` (a
    stg_runtime Camera, pinhole or fisheye), differentiably. options: the torch backend's speed and memory settings
    (rasterize_torch's tile_size, chunk, max_elements, checkpoint); the result never depends on them.
    The numba backend takes CPU tensors only; the backends other than torch take no options."""
    if backend not in SPLATTERS:
        raise ValueError(f"backend must be one of {tuple(SPLATTERS)}, got {backend!r}")
    module, _, function = SPLATTERS[backend].partition(":")
    draw = getattr(importlib.import_module(module), function)
    if backend == "torch":
        return draw(means, quats, scales, opacities, features, camera, **options)
    return draw(means, quats, scales, opacities, features, camera)


def resolve_backend(name: str, device: str) -> str:
    """The backend to train with on `device` ("cpu" or "cuda"): "auto" picks numba on the CPU and gsplat
    on CUDA when it can run (installed, device present), else torch. Raises ValueError with the reason
    when a backend asked for explicitly cannot run there. Other backends of SPLATTERS are taken as named."""
    if name not in ("auto",) + tuple(SPLATTERS):
        raise ValueError(f"splatter must be auto, {', '.join(SPLATTERS)}, got {name!r}")
    if name == "torch":
        return "torch"
    if device == "cpu" and name in ("auto", "numba"):
        return "numba"
    if name == "numba":
        raise ValueError(f"--splatter numba runs on the CPU, not on {device}; use --splatter gsplat, torch or auto")
    if name not in ("auto", "gsplat"):
        return name
    from .gsplat_backend import unavailable_reason

    reason = unavailable_reason(device)
    if name == "auto":
        return "torch" if reason else "gsplat"
    if reason:
        raise ValueError(f"--splatter gsplat: {reason}; use --splatter torch or auto")
    return "gsplat"
