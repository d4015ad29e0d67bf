"""Device memory: buffers kept between frames, and inputs moved to (or found on) the device.

With CuPy installed every buffer comes from CuPy's memory pool: numba's own allocations call cudaMalloc
and cudaFree, and the frees synchronise the device (docs/performance.md has the measured costs). Both libraries
use the default stream here, so their work is ordered.
"""
from __future__ import annotations

import numpy as np
from numba import cuda

from .device import cupy, is_device_array


def _allocate(shape, dtype):
    """(numba device array, the CuPy array it views or None): uninitialised, from CuPy's pool when CuPy
    is in use. The numba view is made without numba's synchronisation on foreign arrays."""
    cp = cupy()
    if cp is None:
        return cuda.device_array(shape, dtype), None
    array = cp.empty(shape, dtype)
    return cuda.as_cuda_array(array, sync=False), array


def device_empty(shape, dtype):
    """An uninitialised device array (numba's type), from CuPy's pool when CuPy is in use."""
    return _allocate(shape, dtype)[0]


def device_f32(x, shape):
    """A contiguous float32 device array of `shape` (-1 allowed) from a host or device array (device
    arrays of that shape are returned as they are). TypeError for device arrays of another dtype."""
    if is_device_array(x):
        d = x if hasattr(x, "copy_to_host") else cuda.as_cuda_array(x)
        if d.dtype != np.float32:
            raise TypeError(f"device inputs must be float32, got {d.dtype}")
        if -1 in shape:
            known = int(np.prod([v for v in shape if v != -1]))
            shape = tuple(d.size // known if v == -1 else v for v in shape)
        return d if d.shape == shape else d.reshape(shape)
    return cuda.to_device(np.ascontiguousarray(np.asarray(x, dtype=np.float32).reshape(shape)))


class Buffer:
    """One workspace buffer: `device` (the numba array), `cupy` (the CuPy array it views, or None), and
    views of its memory made once."""

    __slots__ = ("device", "cupy", "shape", "dtype", "views")

    def __init__(self, shape, dtype):
        self.shape, self.dtype = shape, np.dtype(dtype)
        self.device, self.cupy = _allocate(shape, dtype)
        self.views: dict = {}

    def view(self, dtype, shape):
        """The buffer's memory as `dtype` in `shape` (a numba array, made once)."""
        key = (np.dtype(dtype).char, shape)
        if key not in self.views:
            self.views[key] = self.device.view(dtype).reshape(shape)
        return self.views[key]

    def to_host(self) -> np.ndarray:
        """The buffer's contents on the host (waits for the device)."""
        return self.cupy.get() if self.cupy is not None else self.device.copy_to_host()


class Workspace:
    """Device buffers kept from one call to the next, so that a frame allocates nothing and its kernel
    launches repeat with the same arrays (stg_runtime.cuda.launch replays them).

    The results of cuda.splat.rasterize(..., workspace=ws, out="device") are buffers of ws: the next
    call with ws overwrites them (copy what must be kept). Player keeps one per player. buffer() gives
    callers their own named buffers in the same way (Player's rgb image, say).
    """

    def __init__(self):
        self._buffers: dict[str, Buffer] = {}

    def buffer(self, name: str, shape, dtype, *, at_least: bool = False) -> Buffer:
        """The buffer called `name`: kept while its shape and dtype stay, else a new uninitialised one.
        at_least (1-D only): any length >= shape[0] will do; a new one gets half as much again."""
        shape = tuple(int(v) for v in shape)
        b = self._buffers.get(name)
        if b is not None and b.dtype == dtype and (
                b.shape == shape or (at_least and len(b.shape) == 1 and b.shape[0] >= shape[0])):
            return b
        if at_least:
            shape = (max(shape[0], 1) * 3 // 2 + 256,)
        b = self._buffers[name] = Buffer(shape, dtype)
        return b
