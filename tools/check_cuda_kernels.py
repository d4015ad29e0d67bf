#!/usr/bin/env python
"""Compile every numba.cuda kernel of stg_runtime to PTX without a GPU: numba's typing and lowering for
the CUDA target, which numba's simulator (the CPU test suite's GPU path) never runs.

    python tools/check_cuda_kernels.py [--cc 8.0]

Needs NVIDIA's NVVM compiler library, no GPU and no driver: numba's own CUDA target finds it in a CUDA
toolkit (/usr/local/cuda, or CUDA_HOME); numba-cuda also in its `[cu12]` or `[cu13]` extra's wheels.
Each kernel is compiled for the argument types its Python wrapper launches it with
(listed below: a kernel without an entry is an error, so the list stays complete). Exit status: 0 all
compile, 1 some failed, 2 no NVVM here (nothing was checked). tests/runtime/cuda/test_compile.py runs it.
"""
from __future__ import annotations

import argparse
import sys
import types

from numba import cuda
from numba import types as T

from stg_runtime.projection import CAMERA_PARAMS

f32_1, f32_2, f32_3 = T.float32[::1], T.float32[:, ::1], T.float32[:, :, ::1]
f64_1, f64_2 = T.float64[::1], T.float64[:, ::1]
i32_1, i32_2 = T.int32[::1], T.int32[:, ::1]
i64_1, i64_2 = T.int64[::1], T.int64[:, ::1]
F, I, B = T.float64, T.int64, T.boolean  # Python floats, ints and bools as launch arguments
CAM = T.UniTuple(T.float64, CAMERA_PARAMS)  # projection.camera_params

#: Per module, per kernel: its argument types, or a list of them.
SIGNATURES = {
    "cuda.splat": {
        "_project": (f32_2, f32_2, f32_2, f32_1, CAM, I, I, I, f32_2, i32_2, i32_1, f32_2, i32_2, i64_2, i64_1),
        "_clear": (i64_1,),
        # keys: int32 with CuPy when they fit, else int64
        "_duplicate": [(i32_2, i32_1, i32_2, I, I, i64_1, i32_1), (i32_2, i32_1, i32_2, I, I, i64_1, i64_1)],
        "_ranges": [(i32_1, i32_2, i64_1, i64_2, i32_1), (i64_1, i32_2, i64_1, i64_2, i32_1)],
        "_composite": (f32_2, i32_2, f32_2, i64_2, i32_1, I, I, I, I, f32_3, f32_2, f32_2),
    },
    "cuda.timeeval": {
        "_evaluate": (T.float32, f32_1, f32_1, f32_1, T.float32[:, :, ::1], T.float32[:, :, ::1], f32_2, f32_2,
                      I, f32_2, f32_2, f32_2, f32_1, f32_2),
    },
    "cuda.decoder": {
        "_decode": (f32_3, f32_2, f32_2, CAM, B, f32_3),
        "_decoder_rows": (f32_3, CAM, f32_2),
        "_add_base": (f32_3, f32_2, B, f32_3),
        "_lite": (f32_3, f32_3),
        "_sh": (f32_2, f32_2, CAM, f32_2),
    },
    "cuda.sort": {
        "_scan_tiles": [(i32_1, i64_1, i64_1), (i64_1, i64_1, i64_1)],
        "_add_offsets": (i64_1, i64_1),
        "_histogram": (i64_1, I, i32_1),
        "_scatter": (i64_1, i32_1, B, I, i64_1, i64_1, i32_1),
        "_copy": [(i64_1, i64_1), (i32_1, i32_1)],
    },
}


def _without_driver(cc: tuple[int, int]) -> None:
    """Device functions and overloads are compiled for the "current device": make that a stand-in with
    compute capability `cc`, so that no driver is needed."""
    fake = lambda: types.SimpleNamespace(compute_capability=cc)  # noqa: E731
    for name, module in list(sys.modules.items()):
        if name.startswith("numba.cuda") and hasattr(module, "get_current_device"):
            module.get_current_device = fake


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cc", default="8.0", help="compute capability to compile for (default 8.0)")
    cc = tuple(int(v) for v in ap.parse_args().cc.split("."))
    try:
        from numba.cuda.cudadrv.nvvm import NVVM
        NVVM()
    except Exception as e:  # noqa: BLE001 (any way of not finding it)
        print(f"check_cuda_kernels: NVVM not found, nothing checked ({type(e).__name__}: {str(e).strip()[:300]})")
        return 2
    import importlib
    modules = {name: importlib.import_module(f"stg_runtime.{name}") for name in SIGNATURES}
    _without_driver(cc)
    failed = 0
    for name, module in modules.items():
        kernels = {k: v for k, v in vars(module).items()
                   if hasattr(v, "py_func") and hasattr(v, "targetoptions") and not v.targetoptions.get("device")}
        for kernel in sorted(set(kernels) | set(SIGNATURES[name])):
            sigs = SIGNATURES[name].get(kernel)
            try:
                if sigs is None:
                    raise KeyError("no signature listed in tools/check_cuda_kernels.py")
                for sig in sigs if isinstance(sigs, list) else [sigs]:
                    cuda.compile_ptx(kernels[kernel].py_func, sig, cc=cc)
                print(f"ok      {name}.{kernel}")
            except Exception as e:  # noqa: BLE001 (report every kernel)
                failed += 1
                print(f"FAILED  {name}.{kernel}: {type(e).__name__}: {str(e).strip()[:2000]}")
    print(f"\n{'all kernels compile' if not failed else f'{failed} failed'} (compute capability {cc[0]}.{cc[1]}, "
          f"numba.cuda from {cuda.__file__})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
