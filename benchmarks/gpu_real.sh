#!/usr/bin/env bash
# configs/bench/real.yaml's grid on a lent GPU machine, within one call: build gsplat, then per scene its clean run
# (the degraded data's depth) and its conditions as parallel suite processes, all under one deadline; the results
# (no PLY, no checkpoints) and the logs are tarred into $OUT. Stage the captures first, here:
#   python benchmarks/stage_gpu_captures.py      # writes .gpu/ (carry .gpu and .whl)
# then on the machine: DEADLINE_S=550 bash benchmarks/gpu_real.sh
# JOBS (4) suite processes share the GPU. Local dry test:
#   DEVICE=cpu STEPS=10 SCENES=lund CONDS=fog-200-ind PY=python bash benchmarks/gpu_real.sh
set -u
OUT=${OUT:-/tmp/gpu-out}; mkdir -p "$OUT"
T0=$(date +%s); DEADLINE_S=${DEADLINE_S:-545}
DEVICE=${DEVICE:-cuda}; STEPS=${STEPS:-3000}
SCENES=${SCENES:-ethiopianhead fox lund}
CONDS=${CONDS:-rain+fog-ind fog-200-ind rain-heavy-ind rain-light-ind}  # the independent family first
# PAIRS="lund rain-heavy,fox fog-200-ind" picks (scene, condition) pairs instead of SCENES x CONDS (SCENES still
# names the clean runs)
METHODS=${METHODS:-3dgs-clean 3dgs metegs-blind metegs-blind-stop metegs-blind-nodcp metegs-full}
# the suite processes share the CPU cores: two OpenMP threads each, as spinning threads would stall the others
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
PY=${PY:-python3}
source benchmarks/gpu_env.sh
CFG=.gpu/real-gpu-run.yaml
sed -e "s/device: cuda/device: $DEVICE/" -e "s/max_steps: 3000/max_steps: $STEPS/" -e "s/checkpoint_every: 1000/checkpoint_every: $STEPS/" .gpu/real-gpu.yaml > $CFG
left() { echo $((DEADLINE_S - ($(date +%s) - T0))); }
bench() { timeout "$(left)" $PY -c "import sys; from metegs.cli.bench import entrypoint; sys.argv[0] = 'metegs-bench'; entrypoint()" "$@"; }
echo "runs from $(( $(date +%s) - T0 )) s"
pair() {  # pair SCENE CONDITION: one suite process for the condition's rows (log names avoid '+', refused on return)
  bench suite $CFG --only-scenes "$1" --only-conditions "$2" --only-methods $METHODS > "$OUT/logs/$1-${2//+/-and-}.log" 2>&1
  echo "$1 / $2 ended at $(( $(date +%s) - T0 )) s"
}
export -f pair bench left; export CFG METHODS OUT T0 DEADLINE_S PY
# the clean runs first (each scene's conditions take their depth from it), then the (scene, condition) pairs, at most
# JOBS suite processes at a time: twelve at once on one H200 left every run unfinished after 350 s, and one 3DGS
# run shared with eleven others took 152 s against 28 s shared with two; with five, 3DGS took 52-80 s and blind
# MeteGS 185-229 s (3000 steps), so one 545 s call finishes about five (scene, condition) pairs' first two rows
( for s in $SCENES; do
    bench suite $CFG --only-scenes $s --only-methods 3dgs-clean > "$OUT/logs/clean-$s.log" 2>&1 &
  done; wait; echo "clean runs ended at $(( $(date +%s) - T0 )) s"
  if [ -n "${PAIRS:-}" ]; then echo "$PAIRS" | tr ',' '\n'; else for c in $CONDS; do for s in $SCENES; do echo "$s $c"; done; done; fi |
    xargs -P "${JOBS:-4}" -L 1 bash -c 'pair "$0" "$1"'
) &
WORK=$!
while kill -0 $WORK 2>/dev/null && [ "$(left)" -gt 25 ]; do sleep 5; done
echo "collecting at $(( $(date +%s) - T0 )) s ($(pgrep -fc "metegs.cli.bench") suite processes still running)"
pkill -f "metegs.cli.bench" 2>/dev/null; sleep 2
R=outputs/bench/real-gpu
find $R \( -name '*.json' -o -name '*.yml' -o -name '*.md' -o -name 'preview.png' \) -not -path '*/checkpoints/*' > /tmp/files.txt
find $R -path '*/renders/test/*_compare.png' -path '*metegs-blind/*' | sort | awk -F/ '!seen[$(NF-4)"/"$(NF-3)]++' >> /tmp/files.txt
tar -czf "$OUT/real-gpu.tgz" -T /tmp/files.txt
(cd "$OUT/logs" && tar -czf "$OUT/logs.tgz" . ) && rm -rf "$OUT/logs"
echo "done at $(( $(date +%s) - T0 )) s"; ls -la "$OUT"
for f in $(find $R -name metrics.json | sort); do $PY -c "
import json,sys; m=json.load(open('$f')); print('$f'.split('real-gpu/')[1], round(m['psnr'],2), round(m['ssim'],3), m.get('num_gaussians'), m.get('train_seconds'))"; done
