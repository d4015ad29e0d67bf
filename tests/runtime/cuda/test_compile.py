"""Every numba.cuda kernel compiles for the CUDA target (typing and lowering to PTX), without a GPU:
the check the simulator-run kernel tests (tests/runtime/cuda/test_kernels.py) cannot make. Skipped
where NVIDIA's NVVM library is not installed (a CUDA toolkit, or numba-cuda's [cu12]/[cu13] extra, brings it)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


def test_every_kernel_compiles_to_ptx():
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "check_cuda_kernels.py")], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    if out.returncode == 2:
        pytest.skip(out.stdout.strip())
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-3000:]
    assert "all kernels compile" in out.stdout
    assert out.stdout.count("ok      ") >= 9  # projection, binning, compositing, time, decoders, sort
