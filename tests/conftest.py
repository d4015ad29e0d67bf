"""Shared fixtures. stg_train is imported before any test module imports torch, so that its OpenMP
setting takes effect (see stg_train/__init__.py)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

import stg_train  # noqa: F401

SIMULATOR = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"


def _share_simulated_arrays_safely() -> None:
    """Make numba's simulated cuda.shared.array safe for the threads of a block.

    The simulator runs each CUDA thread of a block as a Python thread. It finds a block's shared array
    in a dict keyed by the calling line, but without a lock. Two threads that both miss create two
    arrays, and then the threads of the first block no longer share memory. The picture of the test
    comes out wrong (seen once in CI, tile 0 of test_player_cuda_matches_cpu). Our short GIL switch
    interval (below) makes this more likely. Here the look-up and the insertion are one locked step,
    with the same key (file, line)."""
    import threading

    import numpy as np
    from numba.core import types
    from numba.cuda.simulator import kernelapi
    from numba.np import numpy_support

    dynamic = kernelapi.FakeCUDAShared.array
    lock = threading.Lock()

    def array(self, shape, dtype):
        if shape == 0:  # dynamic shared memory: one buffer, no look-up
            return dynamic(self, shape, dtype)
        if isinstance(dtype, types.Type):
            dtype = numpy_support.as_dtype(dtype)
        caller = sys._getframe(1)
        key = (caller.f_code.co_filename, caller.f_lineno)
        with lock:
            found = self._allocations.get(key)
            if found is None:
                found = self._allocations[key] = np.empty(shape, dtype)
        return found

    kernelapi.FakeCUDAShared.array = array


if SIMULATOR:
    _share_simulated_arrays_safely()


@pytest.fixture(scope="module")
def two_torch_threads():
    """At most two torch threads for a module's training tests (use with pytest.mark.usefixtures)."""
    import torch
    old = torch.get_num_threads()
    torch.set_num_threads(min(2, old))
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def synthetic_n3v(tmp_path_factory):
    """write(name, **scene) -> the path of a new temporary folder holding stg_train.synthetic's scene
    (seed 0, lasting scene's num_frames / fps seconds) in the N3V layout; scene: write_n3v's keyword
    arguments (num_cameras, num_frames, fps, width, height)."""
    from stg_train.synthetic import SyntheticScene, write_n3v

    def write(name: str, **scene) -> Path:
        path = tmp_path_factory.mktemp(name)
        write_n3v(path, SyntheticScene(seed=0, duration=scene["num_frames"] / scene["fps"]), **scene)
        return path
    return write


@pytest.fixture(autouse=True)
def _fast_simulator_threads():
    """Under numba's CUDA simulator, whose block manager polls its threads, a GIL switch interval shorter
    than the default 5 ms makes barriers several times faster. Restored after each test."""
    old = sys.getswitchinterval()
    if SIMULATOR:
        sys.setswitchinterval(0.0005)
    yield
    sys.setswitchinterval(old)


@pytest.fixture
def run_under_simulator():
    """run(test_file, passed): run a test file again in a subprocess with NUMBA_ENABLE_CUDASIM=1 (which
    must be set before numba.cuda is first imported) and assert that exactly `passed` tests passed."""
    def run(test_file: str, passed: int) -> None:
        env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
        out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test_file],
                             cwd=Path(__file__).resolve().parent.parent, env=env, capture_output=True, text=True,
                             timeout=600)
        assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
        last = out.stdout.strip().splitlines()[-1]
        assert f"{passed} passed" in last and "failed" not in last, last
    return run
