#!/usr/bin/env bash
# Every check that needs a real NVIDIA GPU, in one run of at most GPU_CHECK_SECONDS (default 520; each
# step has its own time limit and none starts past the budget), with its logs in one folder (12 files):
#
#   bash bench/gpu_check.sh [OUTDIR]      (default: $OUT if set, else out/gpu_check)
#
# 1. the GPU tests: tests/runtime/cuda/ (test_kernels.py and test_sort.py run their kernels on the GPU,
#    not the simulator; test_launch.py, test_compile.py);
# 2. bench/render.py --device cuda at the paper's N3V test size (200k Gaussians, 1352x1014) on the random
#    scene (the scene of the earlier figures): FPS of lite and full models, the steps, both device sorts
#    and decoders; then the same on scenes like trained ones (render_like_trained.log: like_trained_model
#    at 100k / 200k / 500k Gaussians, 640x360 and 1352x1014, each figure with its layers per pixel), and
#    on the trained demo model when out/bench_cache/demo-{lite,full}/model.stg were carried along
#    (render_trained.log; `python bench/render.py --scene trained` makes them here);
#    bench/gpu_profile.py: each kernel's GPU time against the frame's wall-clock time, and the host's
#    cost per call;
# 3. gsplat: its CUDA kernels are built (gsplat_build.log) in the background from the start, on the
#    cores our steps leave idle; then tests/train/test_render_gsplat.py compares it with the torch splatter,
#    and the render benchmark runs again with gsplat's rasterization beside ours;
# 4. bench/scale.py at the N3V size (20 cameras x 50 frames at 1352x1014, one segment; scale.log), if
#    time is left and GPU_CHECK_SCALE is not 0: generation and decoding on the host, then seconds per
#    step and GPU peak memory with gsplat and with the torch splatter, and segment 0 trained for
#    GPU_CHECK_SCALE_ITERATIONS steps (default 1000; the reference schedule's 30000 need their own run:
#    `python bench/scale.py --frames 50 --no-cpu --no-whole`) with its held-out PSNR; then
#    bench/step_profile.py: a gsplat step's GPU time by op (step_profile.log). Both need about 260 s:
#    give the script GPU_CHECK_SECONDS=580 (or GPU_CHECK_TRAIN=0) for it to be reached;
# 5. bench/train.py on the GPU with the torch splatter and with gsplat (a short run, both in train.log),
#    if time is left and GPU_CHECK_TRAIN is not 0.
#
# It uses the checkout in place (PYTHONPATH, no install). Wheels in .whl/ (gsplat, say: `pip download
# --no-deps gsplat==1.5.3 -d .whl`) are installed into a scratch folder, ahead of the installed
# packages: numba-cuda 0.30.4 fails with numpy 2.5, so where numpy 2.5 is installed carry a numpy 2.4
# wheel too. The script's status is that of our GPU tests.
set -u
if ! command -v nvidia-smi >/dev/null; then
    echo "bench/gpu_check.sh: no NVIDIA GPU here (nvidia-smi not found); nothing run" >&2
    exit 2
fi
out=${1:-${OUT:-out/gpu_check}}
mkdir -p "$out"
budget=${GPU_CHECK_SECONDS:-520}
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-python3}

# step LIMIT LOG CMD...: run CMD for at most LIMIT seconds and what is left of the budget, its output
# also in $out/LOG; skipped when under 20 seconds are left.
step() {
    local limit=$1 log=$2 left=$((budget - SECONDS - 5))
    shift 2
    if ((left < 20)); then
        echo "skipped (out of time): $*" | tee "$out/$log"
        return 124
    fi
    timeout $((limit < left ? limit : left)) "$@" 2>&1 | tee "$out/$log"
    return "${PIPESTATUS[0]}"
}

if compgen -G ".whl/*.whl" >/dev/null; then
    $py -m pip install -q --no-index --no-deps --no-compile --target /tmp/stg_site .whl/*.whl \
        && export PYTHONPATH="$PYTHONPATH:/tmp/stg_site"
fi
# gsplat compiles its CUDA kernels on first use (minutes): start that now, for this GPU only.
arch=$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader | head -1)
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$arch} MAX_JOBS=${MAX_JOBS:-12}
nice -n 10 timeout $((budget - 150)) $py -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat kernels', 'built' if _C is not None else 'NOT built', f'in {time.time() - t:.0f} s')" \
    >"$out/gsplat_build.log" 2>&1 &
build=$!

{ nvidia-smi --query-gpu=name,driver_version,memory.total,compute_cap --format=csv
  $py -c "import numba, numpy, onnxruntime as o; print('numba', numba.__version__, 'numpy', numpy.__version__,
'onnxruntime', o.__version__, o.get_available_providers())"
  $py -m pip list 2>/dev/null | grep -i -E "^(numba-cuda|cupy|torch) "
} 2>&1 | tee "$out/gpu.txt"

# Ours first, so that gsplat's build cannot cost our figures.
step 100 tests.log $py -m pytest -q -rs -p no:cacheprovider tests/runtime/cuda
status=$?
step 80 render.log $py bench/render.py --device cuda --scene random --gaussians 200000 --size 1352x1014 --repeats 30 \
    --no-gsplat
step 120 render_like_trained.log $py bench/render.py --device cuda --scene like-trained --gaussians 100000,200000,500000 \
    --size 640x360,1352x1014 --repeats 20 --no-gsplat
if [[ -f out/bench_cache/demo-lite/model.stg && -f out/bench_cache/demo-full/model.stg ]]; then
    step 40 render_trained.log $py bench/render.py --device cuda --scene trained --size 640x360,1352x1014 \
        --repeats 20 --no-gsplat
fi
step 60 profile.log $py bench/gpu_profile.py --gaussians 200000 --size 1352x1014

# gsplat: wait for its build (leaving two minutes for what follows), its GPU test, then the render
# benchmark again with gsplat beside ours.
while kill -0 $build 2>/dev/null && ((SECONDS < budget - 120)); do sleep 2; done
kill $build 2>/dev/null && echo "gsplat build stopped: out of time" >>"$out/gsplat_build.log"
step 50 tests_gsplat.log $py -m pytest -q -rs -p no:cacheprovider tests/train/test_render_gsplat.py
step 70 render_gsplat.log $py bench/render.py --device cuda --scene random --gaussians 200000 --size 1352x1014 --repeats 20

if [[ ${GPU_CHECK_SCALE:-1} != 0 ]]; then
    step 220 scale.log $py bench/scale.py --frames 50 --no-cpu --no-whole --steps 10 --threads 16 \
        --segment-iterations "${GPU_CHECK_SCALE_ITERATIONS:-1000}" --data /tmp/stg_scale
    step 60 step_profile.log $py bench/step_profile.py --device cuda --splatter gsplat --width 1352 --height 1014 \
        --steps 10 --threads 16 --ops 25
fi

if [[ ${GPU_CHECK_TRAIN:-1} != 0 ]]; then
    step 40 train_torch.log $py bench/train.py --device cuda --splatter torch --threads 16 \
        --iterations 300 --eval-every 100 --data /tmp/stg_scene
    step 40 train_gsplat.log $py bench/train.py --device cuda --splatter gsplat --threads 16 \
        --iterations 300 --eval-every 100 --data /tmp/stg_scene
    cat "$out/train_torch.log" "$out/train_gsplat.log" >"$out/train.log" && rm "$out/train_torch.log" "$out/train_gsplat.log"
fi
exit "$status"
