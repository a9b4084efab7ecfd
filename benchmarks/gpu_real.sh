#!/usr/bin/env bash
# configs/bench/real.yaml's grid on a lent GPU machine, within one call: build gsplat, then per scene its clean run
# (the degraded data's depth) and its conditions as parallel suite processes, all under one deadline; the results
# (no PLY, no checkpoints) and the logs are tarred into $OUT. Stage the captures first, here:
#   python benchmarks/stage_gpu_captures.py      # writes .gpu/ (carry .gpu and .whl)
# then on the machine: DEADLINE_S=550 bash benchmarks/gpu_real.sh
# Local dry test: DEVICE=cpu STEPS=10 SCENES=lund CONDS=fog-200-ind PY=python bash benchmarks/gpu_real.sh
set -u
OUT=${OUT:-/tmp/gpu-out}; mkdir -p "$OUT"
T0=$(date +%s); DEADLINE_S=${DEADLINE_S:-545}
DEVICE=${DEVICE:-cuda}; STEPS=${STEPS:-3000}
SCENES=${SCENES:-ethiopianhead fox lund}
CONDS=${CONDS:-rain+fog-ind fog-200-ind rain-heavy-ind rain-light-ind}  # the independent family first
METHODS=${METHODS:-3dgs-clean 3dgs metegs-blind metegs-blind-nodcp metegs-full}
if [ "$DEVICE" = cuda ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || { echo "wheels failed"; exit 1; }
  export PYTHONPATH=/tmp/site:$PWD
  export TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
fi
export PYTHONUNBUFFERED=1 MAX_JOBS=$(nproc) TORCH_EXTENSIONS_DIR=/tmp/torch_ext
PY=${PY:-python3}
CFG=.gpu/real-gpu-run.yaml
sed -e "s/device: cuda/device: $DEVICE/" -e "s/max_steps: 3000/max_steps: $STEPS/" -e "s/checkpoint_every: 1000/checkpoint_every: $STEPS/" .gpu/real-gpu.yaml > $CFG
left() { echo $((DEADLINE_S - ($(date +%s) - T0))); }
bench() { timeout "$(left)" $PY -c "import sys; from metegs.cli.bench import entrypoint; sys.argv[0] = 'metegs-bench'; entrypoint()" "$@"; }
mkdir -p "$OUT/logs"
{ nvidia-smi -L 2>/dev/null; $PY -c "import torch; print(torch.__version__, torch.cuda.is_available())"; } > "$OUT/logs/env.log" 2>&1
if [ "$DEVICE" = cuda ]; then
  timeout 200 $PY -c "
import time; t = time.time()
from metegs.render.gsplat_backend import load_gsplat
g = load_gsplat(); print('gsplat', g.__version__, 'built in %.0f s' % (time.time() - t))" > "$OUT/logs/build.log" 2>&1
  tail -n 3 "$OUT/logs/build.log"
fi
echo "runs from $(( $(date +%s) - T0 )) s"
for s in $SCENES; do  # per scene: its clean run (the degraded data's depth), then its conditions in parallel
  ( bench suite $CFG --only-scenes $s --only-methods 3dgs-clean > "$OUT/logs/clean-$s.log" 2>&1
    echo "$s: clean run ended at $(( $(date +%s) - T0 )) s"
    for c in $CONDS; do
      bench suite $CFG --only-scenes $s --only-conditions $c --only-methods $METHODS > "$OUT/logs/$s-$c.log" 2>&1 &
    done; wait ) &
done
while [ "$(jobs -r | wc -l)" -gt 0 ] && [ "$(left)" -gt 25 ]; do sleep 5; done
echo "collecting at $(( $(date +%s) - T0 )) s ($(jobs -r | wc -l) still running)"
pkill -f "metegs.cli.bench" 2>/dev/null; sleep 2
R=outputs/bench/real-gpu
find $R \( -name '*.json' -o -name '*.yml' -o -name '*.md' -o -name 'preview.png' \) -not -path '*/checkpoints/*' > /tmp/files.txt
find $R -path '*/renders/test/*_compare.png' -path '*metegs-blind/*' | sort | awk -F/ '!seen[$(NF-4)"/"$(NF-3)]++' >> /tmp/files.txt
tar -czf "$OUT/real-gpu.tgz" -T /tmp/files.txt
(cd "$OUT/logs" && tar -czf "$OUT/logs.tgz" . ) && rm -rf "$OUT/logs"
echo "done at $(( $(date +%s) - T0 )) s"; ls -la "$OUT"
for f in $(find $R -name metrics.json | sort); do $PY -c "
import json,sys; m=json.load(open('$f')); print('$f'.split('real-gpu/')[1], round(m['psnr'],2), round(m['ssim'],3), m.get('num_gaussians'), m.get('train_seconds'))"; done
