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
# names the clean runs); ROWS_APART=1 runs each (pair, row) as its own process, METHODS's first row writing the
# pair's degraded photos. On a just-started machine gsplat's build takes up to 314 s of a call's 600: there a first
# call with PREP=1 builds it, trains the clean runs and writes the pairs' degraded photos, and a second one (at once:
# an idle machine goes back after 30 s) trains the rows, e.g. (one H200, 2026-12-04: three blind and three 3DGS
# Lund runs, 3000 steps, in 155 s):
#   PREP=1 PAIRS="lund rain-heavy" SCENES=lund METHODS="metegs-blind 3dgs" DEADLINE_S=560 bash benchmarks/gpu_real.sh
#   PAIRS=... SCENES=lund ROWS_APART=1 METHODS="metegs-blind metegs-blind-seed1 ..." JOBS=6 bash benchmarks/gpu_real.sh
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
pair() {  # pair SCENE CONDITION [ROW]: one suite process for the condition's rows, or with ROW for that row alone,
  # started once the cell's degraded photos exist (its first row's process writes them; two would race)
  local rows=${3:-$METHODS} log="$1-${2//+/-and-}${3:+-$3}"  # log names avoid '+', refused on return
  if [ -n "${3:-}" ] && [ "$3" != "${METHODS%% *}" ]; then
    until [ -f "$R/$1/$2/data/weather.json" ]; do [ "$(left)" -gt 30 ] || return; sleep 2; done
  fi
  bench suite $CFG --only-scenes "$1" --only-conditions "$2" --only-methods $rows > "$OUT/logs/$log.log" 2>&1
  echo "$1 / $2 ${3:-} ended at $(( $(date +%s) - T0 )) s"
}
R=outputs/bench/real-gpu
export -f pair bench left; export CFG METHODS OUT T0 DEADLINE_S PY R
# the clean runs first (each scene's conditions take their depth from it), then the (scene, condition) pairs, at most
# JOBS suite processes at a time: twelve at once on one H200 left every run unfinished after 350 s, and one 3DGS
# run shared with eleven others took 152 s against 28 s shared with two; with five, 3DGS took 52-80 s and blind
# MeteGS 185-229 s (3000 steps), so one 545 s call finishes about five (scene, condition) pairs' first two rows
pairs() { if [ -n "${PAIRS:-}" ]; then echo "$PAIRS" | tr ',' '\n'; else for c in $CONDS; do for s in $SCENES; do echo "$s $c"; done; done; fi; }
( for s in $SCENES; do
    if [ -n "${PREP:-}" ]; then  # PREP=1: each scene's clean run and its pairs' degraded photos, no weather run
      conds=$(pairs | awk -v s="$s" '$1 == s { print $2 }')
      bench suite $CFG --only-scenes $s ${conds:+--only-conditions $conds} --only-methods 3dgs-clean $METHODS --prepare \
        > "$OUT/logs/prepare-$s.log" 2>&1 &
    else
      bench suite $CFG --only-scenes $s --only-methods 3dgs-clean > "$OUT/logs/clean-$s.log" 2>&1 &
    fi
  done; wait; echo "clean runs ended at $(( $(date +%s) - T0 )) s"
  [ -n "${PREP:-}" ] && exit
  pairs |
    if [ -n "${ROWS_APART:-}" ]; then  # a process per (pair, row): every pair's first row, then the other rows
      awk -v rows="$METHODS" 'NF { n = split(rows, r, " "); p[++k] = $0 } END {
        for (j = 1; j <= n; j++) for (i = 1; i <= k; i++) print p[i], r[j] }'
    else cat; fi |
    xargs -P "${JOBS:-4}" -L 1 bash -c 'pair "$0" "$1" "${2:-}"'
) &
WORK=$!
while kill -0 $WORK 2>/dev/null && [ "$(left)" -gt 25 ]; do sleep 5; done
echo "collecting at $(( $(date +%s) - T0 )) s ($(pgrep -fc "metegs.cli.bench") suite processes still running)"
pkill -f "metegs.cli.bench" 2>/dev/null; sleep 2
find $R \( -name '*.json' -o -name '*.yml' -o -name '*.md' -o -name 'preview.png' \) -not -path '*/checkpoints/*' > /tmp/files.txt
find $R -path '*/renders/test/*_compare.png' -path '*metegs-blind/*' | sort | awk -F/ '!seen[$(NF-4)"/"$(NF-3)]++' >> /tmp/files.txt
tar -czf "$OUT/real-gpu.tgz" -T /tmp/files.txt
(cd "$OUT/logs" && tar -czf "$OUT/logs.tgz" . ) && rm -rf "$OUT/logs"
echo "done at $(( $(date +%s) - T0 )) s"; ls -la "$OUT"
for f in $(find $R -name metrics.json | sort); do $PY -c "
import json,sys; m=json.load(open('$f')); print('$f'.split('real-gpu/')[1], round(m['psnr'],2), round(m['ssim'],3), m.get('num_gaussians'), m.get('train_seconds'))"; done
