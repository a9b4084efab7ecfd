# Sourced by the scripts for a lent GPU machine (gpu_real.sh, gpu_steps.sh): with DEVICE=cuda, installs the carried
# wheels (.whl/) once per machine, as reinstalling renews gsplat's sources, which rebuilds it (75 s), and points
# Python at them; logs the machine to $OUT/logs/env.log and builds gsplat's kernels ($OUT/logs/build.log).
# Expects DEVICE, OUT and PY; exits when the wheels cannot be installed or gsplat does not build (BUILD_S, 400 s: from
# scratch it took 84-104 s on a warm H200 and 200-314 s on one just started), since every run would otherwise fall
# back to the torch rasteriser, about 10x slower, and spend the lease without a result. The build stays on the machine
# while it is warm (a later call loads it in about 6 s), so on a fresh machine a first call of BUILD_S builds it and
# the grid goes in a second call at once (a machine left idle for 30 s goes back).
mkdir -p "$OUT/logs"
if [ "$DEVICE" = cuda ]; then
  [ -d /tmp/site/gsplat ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || { echo "wheels failed"; exit 1; }
  export PYTHONPATH=/tmp/site:$PWD
  export TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
fi
# nproc --all: plain nproc prints OMP_NUM_THREADS (gpu_real.sh sets 2), and gsplat then built on 2 jobs
export PYTHONUNBUFFERED=1 MAX_JOBS=$(nproc --all) TORCH_EXTENSIONS_DIR=/tmp/torch_ext
{ nvidia-smi -L 2>/dev/null; $PY -c "import torch; print(torch.__version__, torch.cuda.is_available())"; } > "$OUT/logs/env.log" 2>&1
if [ "$DEVICE" = cuda ]; then
  timeout "${BUILD_S:-400}" $PY -c "
import time; t = time.time()
from metegs.render.gsplat_backend import load_gsplat
g = load_gsplat(); print('gsplat', g.__version__, 'built in %.0f s' % (time.time() - t))" > "$OUT/logs/build.log" 2>&1 ||
    { tail -n 3 "$OUT/logs/build.log"; echo "gsplat did not build within ${BUILD_S:-400} s: stopping"; exit 1; }
  tail -n 3 "$OUT/logs/build.log"
fi
