"""Whether the GPU kernels can run here, and the optional CuPy.

Under numba's simulator (NUMBA_ENABLE_CUDASIM=1, set before numba.cuda is first imported) the kernels
run on the CPU, slowly: the tests use it on tiny images. The simulator never counts as a GPU for
device="auto".
"""
from __future__ import annotations

import numpy as np
from numba import config as _numba_config
from numba import cuda

_GPU: list = []
_CUPY: list = []


def simulated() -> bool:
    """Whether numba.cuda is numba's CPU simulator (NUMBA_ENABLE_CUDASIM=1)."""
    return bool(_numba_config.ENABLE_CUDASIM)


def gpu_available() -> bool:
    """Whether numba sees a real CUDA GPU (never true under the simulator); asked once per process."""
    if simulated():
        return False
    if not _GPU:
        try:
            _GPU.append(bool(cuda.is_available()))
        except Exception:  # noqa: BLE001 (a broken driver counts as no GPU)
            _GPU.append(False)
    return _GPU[0]


def usable() -> bool:
    """Whether the kernels can run here: a real GPU, or the simulator."""
    return simulated() or gpu_available()


def require() -> None:
    """Raise RuntimeError, saying why, unless the kernels can run here."""
    if not usable():
        raise RuntimeError("device 'cuda': numba sees no CUDA GPU (no NVIDIA driver/GPU, or the CUDA "
                           "toolkit is missing); use device='cpu', or set NUMBA_ENABLE_CUDASIM=1 before "
                           "starting Python to run the GPU kernels in numba's (slow) CPU simulator")


def cupy():
    """The cupy module when it imports and a real GPU is used (its sort and memory pool), else None."""
    if not _CUPY:
        try:
            import cupy as module  # type: ignore
        except Exception:  # noqa: BLE001 (ImportError, or a CuPy without its CUDA libraries)
            module = None
        _CUPY.append(None if simulated() else module)
    return _CUPY[0]


def is_device_array(x) -> bool:
    """Whether x is a device array (numba's, CuPy's, any __cuda_array_interface__; the simulator's)."""
    if isinstance(x, np.ndarray):
        return False
    return (getattr(type(x), "__cuda_array_interface__", None) is not None or hasattr(x, "__cuda_array_interface__")
            or (simulated() and hasattr(x, "copy_to_host")))
