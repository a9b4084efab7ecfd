#!/usr/bin/env bash
# The checks for a lent CUDA machine, in order of value, each under its own time limit, all within one call:
# build gsplat's kernels, run the gsplat backend's tests, time the rasteriser and training steps on the GPU,
# train the default `metegs-train metegs-full` there, then run the CPU-written test suite with CUDA visible.
#
# Usage (repository root, on the GPU machine): OUT=/tmp/gpu-check DEADLINE_S=560 bash benchmarks/gpu_check.sh
# STAGES="build step suite" runs some of them (build is needed by every later stage: gsplat compiles on first use).
# Wheels for packages the machine lacks (gsplat, tyro, pycolmap for the start of captures without points, ...) are
# installed from .whl/ when it exists. gsplat builds first and alone: its first use deletes its build folder.
# Logs go to $OUT/<stage>.log (at most 8 files); a short summary is printed last.
set -u
OUT=${OUT:-/tmp/gpu-check}
DEADLINE_S=${DEADLINE_S:-560}
STAGES=${STAGES:-build tests raster train step refusals suite}
mkdir -p "$OUT"
T0=$(date +%s)
SUMMARY=()

if ls .whl/*.whl >/dev/null 2>&1; then  # once per machine: reinstalling renews gsplat's sources, which rebuilds it
    [ -d /tmp/site/gsplat ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || { echo "wheel install failed"; exit 1; }
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1 MAX_JOBS=$(nproc --all) TORCH_EXTENSIONS_DIR=/tmp/torch_ext  # shared with gpu_real.sh
export TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())" 2>/dev/null)
export PY=python3 COLUMNS=160  # rich tables whole in the logs

stage() {  # stage NAME LIMIT_S COMMAND...
    local name=$1 limit=$2 left start rc
    shift 2
    [[ " $STAGES " == *" $name "* ]] || return
    left=$((DEADLINE_S - ($(date +%s) - T0) - 5))
    ((left < limit)) && limit=$left
    if ((limit < 10)); then SUMMARY+=("$name: skipped (deadline)"); return; fi
    start=$(date +%s)
    echo "== $name (limit ${limit} s)"
    timeout "$limit" bash -c '"$@"' "$name" "$@" >"$OUT/$name.log" 2>&1
    rc=$?
    SUMMARY+=("$name: rc=$rc in $(($(date +%s) - start)) s")
    tail -n 25 "$OUT/$name.log"
}

cli() {  # cli MODULE ARGS...: a console entry point without installing the package
    local module=$1
    shift
    $PY -c "import sys; from metegs.cli.$module import entrypoint; sys.argv[0] = 'metegs-$module'; entrypoint()" "$@"
}
export -f cli

{
    nvidia-smi
    $PY -c "import torch, sys; print(sys.version); print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name())"
    nvcc --version | tail -n 2
    c++ --version | head -n 1  # the compiler of the cpu extension there, and torch's own
    $PY -c "import torch; print(torch.__config__.show())" | grep -oE "CXX_COMPILER=[^,]*"
    echo "TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST MAX_JOBS=$MAX_JOBS"
} >"$OUT/env.log" 2>&1
cat "$OUT/env.log"

stage build 330 $PY -c "
import time; t = time.time()
from metegs.render.gsplat_backend import load_gsplat
g = load_gsplat(); print('gsplat', g.__version__, 'built and smoke-tested in %.0f s' % (time.time() - t))"
stage tests 90 $PY -m pytest -q -p no:cacheprovider tests/render/test_gsplat_backend.py
stage raster 90 cli bench raster --device cuda --output "$OUT/raster.json"  # the figures, whatever the log width
stage train 240 cli train metegs-full --experiment-name gpu-check
RUN=$(ls -td outputs/*/*/*/ 2>/dev/null | head -n 1)
[ -n "$RUN" ] && find "$RUN" \( -name '*.json' -o -name '*.yml' \) -print0 | tar -czf "$OUT/train-run.tgz" --null -T -
stage step 150 cli bench step --device cuda --output "$OUT/step.json"
# where a cpu kernel refuses bad input its TORCH_CHECK must raise; two xdist workers died there on an H100 (2026-12-05)
stage refusals 60 $PY -m pytest -q -p no:cacheprovider -s tests/losses/test_fused_opening.py::test_bad_input_is_refused_by_the_kernel \
    tests/losses/test_fused_ssim.py::test_bad_shapes_are_refused_by_the_kernel
stage suite 300 $PY -m pytest -q -p no:cacheprovider -n "$(nproc)" -m "not data"

echo "== summary ($(($(date +%s) - T0)) s)"
printf '%s\n' "${SUMMARY[@]}"
