#!/usr/bin/env bash
# Every check that needs a real NVIDIA GPU, in one run (at most 9.5 minutes: each step has its own time
# limit), with its logs in one folder (at most 8 files):
#
#   bash bench/gpu_check.sh [OUTDIR]      (default: $OUT if set, else out/gpu_check)
#
# 1. the GPU tests: tests/test_splat_cuda.py and tests/test_sort_cuda.py run their kernels on the GPU
#    (not the simulator);
# 2. bench/render.py --device cuda at the paper's N3V test size (200k Gaussians, 1352x1014): FPS of
#    lite and full models, the steps, both device sorts and decoders;
# 3. gsplat (its kernels compile on first use): tests/test_gsplat_backend.py compares it with the torch
#    splatter, then the render benchmark again with gsplat's rasterization beside ours;
# 4. bench/train.py on the GPU with the torch splatter and with gsplat (a short run).
#
# It uses the checkout in place (PYTHONPATH, no install). Wheels in .whl/ (gsplat, say: `pip download
# --no-deps gsplat==1.5.3 -d .whl`) are installed into a scratch folder first. Each step has its own
# time limit, so one slow step cannot eat the others' time; the script's status is that of our GPU tests.
set -u
if ! command -v nvidia-smi >/dev/null; then
    echo "bench/gpu_check.sh: no NVIDIA GPU here (nvidia-smi not found); nothing run" >&2
    exit 2
fi
out=${1:-${OUT:-out/gpu_check}}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null; then
    $py -m pip install -q --no-index --no-deps --no-compile --target /tmp/stg_site .whl/*.whl \
        && export PYTHONPATH="$PYTHONPATH:/tmp/stg_site"
fi
export MAX_JOBS=${MAX_JOBS:-16}  # gsplat's first use compiles its CUDA kernels

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  $py -c "import numba, numpy, onnxruntime as o; print('numba', numba.__version__, 'numpy', numpy.__version__,
'onnxruntime', o.__version__, o.get_available_providers())"
  $py -c "import cupy; print('cupy', cupy.__version__)" 2>&1 | tail -1
} 2>&1 | tee "$out/gpu.txt"

# Ours first, so that gsplat's build (minutes, on its first use) cannot cost our figures.
timeout 120 $py -m pytest -q -rs -p no:cacheprovider tests/test_splat_cuda.py tests/test_sort_cuda.py 2>&1 \
    | tee "$out/tests.log"
status=${PIPESTATUS[0]}
timeout 90 $py bench/render.py --device cuda --gaussians 200000 --size 1352x1014 --repeats 30 --no-gsplat \
    2>&1 | tee "$out/render.log"

# gsplat: its build and GPU test, then the render benchmark again with gsplat beside ours.
timeout 190 $py -m pytest -q -rs -p no:cacheprovider tests/test_gsplat_backend.py 2>&1 | tee "$out/tests_gsplat.log"
timeout 80 $py bench/render.py --device cuda --gaussians 200000 --size 1352x1014 --repeats 30 2>&1 \
    | tee "$out/render_gsplat.log"

for splatter in torch gsplat; do
    timeout 40 $py bench/train.py --device cuda --splatter $splatter --threads 16 --iterations 300 \
        --eval-every 100 --data /tmp/stg_scene 2>&1 | tee "$out/train_$splatter.log"
done
exit "$status"
