"""Differentiable rendering for training: one `rasterize`, two backends.

    rasterize(means, quats, scales, opacities, features, camera, backend="torch") -> RenderOutput

    resolve_backend(name, device) -> "numba", "torch" or "gsplat"

Backends: "numba" (stg_train.render.numba_splat, the CPU training splatter: numba kernels with a
backward pass), "torch" (stg_train.render.torch_splat, the readable reference, any device) and "gsplat"
(stg_train.render.gsplat_backend, gsplat's CUDA kernels). numba and gsplat are imported only when used.
All follow formats/stg-v1.md, section 3, and return the same RenderOutput. Cameras may be pinhole or
fisheye (stg_runtime Camera.model): torch and numba draw both; gsplat draws pinholes and equidistant
fisheyes and hands a fisheye with k1..k4 to the torch splatter (gsplat_backend's docstring says why;
docs/training.md, "Camera models").
"""
from __future__ import annotations

from torch import Tensor

from .output import RenderOutput
from .torch_splat import rasterize_torch

BACKENDS = ("numba", "torch", "gsplat")

__all__ = ["BACKENDS", "RenderOutput", "rasterize", "resolve_backend"]


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor, camera,
              *, backend: str = "torch", **options) -> RenderOutput:
    """Render M Gaussians (means (M, 3) world, quats (M, 4) wxyz, scales (M, 3) standard deviations,
    opacities (M,) or (M, 1), features (M, C); one device and float dtype) seen by `camera` (a
    stg_runtime Camera, pinhole or fisheye), differentiably. options: the torch backend's speed and memory settings
    (rasterize_torch's tile_size, chunk, max_elements, checkpoint); the result never depends on them.
    The numba backend takes CPU tensors only."""
    if backend == "torch":
        return rasterize_torch(means, quats, scales, opacities, features, camera, **options)
    if backend == "numba":
        from .numba_splat import rasterize_numba

        return rasterize_numba(means, quats, scales, opacities, features, camera)
    if backend == "gsplat":
        from .gsplat_backend import rasterize_gsplat

        return rasterize_gsplat(means, quats, scales, opacities, features, camera)
    raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def resolve_backend(name: str, device: str) -> str:
    """The backend to train with on `device` ("cpu" or "cuda"): "auto" picks numba on the CPU and gsplat
    on CUDA when it can run (installed, device present), else torch. Raises ValueError with the reason
    when a backend asked for explicitly cannot run there."""
    if name not in ("auto",) + BACKENDS:
        raise ValueError(f"splatter must be auto, {', '.join(BACKENDS)}, got {name!r}")
    if name == "torch":
        return "torch"
    if device == "cpu" and name in ("auto", "numba"):
        return "numba"
    if name == "numba":
        raise ValueError(f"--splatter numba runs on the CPU, not on {device}; use --splatter gsplat, torch or auto")
    from .gsplat_backend import unavailable_reason

    reason = unavailable_reason(device)
    if name == "auto":
        return "torch" if reason else "gsplat"
    if reason:
        raise ValueError(f"--splatter gsplat: {reason}; use --splatter torch or auto")
    return "gsplat"
