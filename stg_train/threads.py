"""CPU threads of a training process: torch's and numba's (the CPU splatter's kernels) together."""
from __future__ import annotations


def set_cpu_threads(n: int) -> None:
    """Use n threads for torch's CPU operations and for numba's parallel kernels (at most the
    NUMBA_NUM_THREADS numba started with). numba's setting holds for the calling thread."""
    import numba
    import torch

    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
