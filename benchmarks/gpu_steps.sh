#!/usr/bin/env bash
# Test PSNR of `3dgs` as steps grow (2000 / 7000 / 30000) on the staged Lund street (23 training and 4 test views,
# 510x382, clean photos, SfM points), on a lent GPU machine within one call. Stage first, here:
#   python benchmarks/stage_gpu_captures.py        # writes .gpu/ (carry .gpu and .whl)
# then on the machine: DEADLINE_S=540 bash benchmarks/gpu_steps.sh
# PLAN lists the runs, one per line: steps, seed, a name for the variant and its extra `metegs-train` options;
# JOBS (2) of them share the GPU at a time, in order (the default: the 30000-step run beside the 2000- and
# 7000-step runs of seeds 0 and 1, then a 15000-step run as time allows).
# Each run evaluates its test views along the way (history in metrics.json and in each checkpoint), so a run the
# deadline stops still leaves its curve: the newest checkpoint's history is written as history-<run>.json.
# Local dry test: DEVICE=cpu SCALE=100 PY=python bash benchmarks/gpu_steps.sh   (steps divided by SCALE)
set -u
OUT=${OUT:-/tmp/gpu-out}
T0=$(date +%s); DEADLINE_S=${DEADLINE_S:-540}
DEVICE=${DEVICE:-cuda}; SCALE=${SCALE:-1}; PY=${PY:-python3}
DATA=${DATA:-.gpu/data/lund}; RUNS=/tmp/steps-runs
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-4}
source benchmarks/gpu_env.sh
left() { echo $((DEADLINE_S - ($(date +%s) - T0))); }
echo "runs from $(( $(date +%s) - T0 )) s"
PLAN=${PLAN:-"30000 0 default
2000 0 default
7000 0 default
2000 1 default
7000 1 default
15000 0 default"}
run() {  # run STEPS SEED VARIANT [EXTRA...]: one 3dgs run, evaluated 15 times along the way, checkpointed 10 times
  local steps=$(( $1 / SCALE )) seed=$2 variant=$3; shift 3
  local name="${variant}-s${steps}-seed${seed}"
  [ "$(left)" -gt 20 ] || return
  timeout "$(( $(left) - 15 ))" $PY -c "import sys; from metegs.cli.train import entrypoint; sys.argv[0] = 'metegs-train'; entrypoint()" \
    3dgs --data "$DATA" --device "$DEVICE" --max-steps "$steps" --seed "$seed" --eval-every 0.0667 \
    --checkpoint-every $(( steps / 10 > 0 ? steps / 10 : 1 )) --no-lpips-download --no-progress \
    --output-dir $RUNS --experiment-name "$name" "$@" > "$OUT/logs/$name.log" 2>&1
  echo "$name ended (rc $?) at $(( $(date +%s) - T0 )) s"
}
export -f run left; export SCALE T0 DEADLINE_S PY DATA DEVICE RUNS OUT
echo "$PLAN" | xargs -P "${JOBS:-2}" -L 1 bash -c 'run "$@"' run &
WORK=$!
while kill -0 $WORK 2>/dev/null && [ "$(left)" -gt 12 ]; do sleep 3; done
pkill -f "metegs.cli.train" 2>/dev/null; sleep 2
echo "collecting at $(( $(date +%s) - T0 )) s"
$PY - "$RUNS" "$OUT" <<'EOF'
import json, sys
from pathlib import Path
import torch
runs, out = Path(sys.argv[1]), Path(sys.argv[2])
for run in sorted(p for p in runs.glob("*/3dgs/*") if p.is_dir()):
    m = run / "metrics.json"
    if m.is_file():
        d = json.loads(m.read_text())
        (out / f"metrics-{run.name}.json").write_text(json.dumps(d, indent=1))
        print(run.name, "final", round(d["psnr"], 2), round(d["ssim"], 3), d["num_gaussians"], d["train_seconds"])
        hist = d["history"]
    else:
        ckpts = sorted((run / "checkpoints").glob("step-*.ckpt"))
        if not ckpts:
            continue
        hist = torch.load(ckpts[-1], map_location="cpu", weights_only=False).get("history", [])
        print(run.name, "stopped at", ckpts[-1].name)
    (out / f"history-{run.name}.json").write_text(json.dumps(hist, indent=1))
    print("  " + "  ".join(f"{h['step']}:{h['psnr']:.2f}/{h['num_gaussians'] // 1000}k" for h in hist))
EOF
(cd "$OUT/logs" && tar -czf "$OUT/logs.tgz" . ) && rm -rf "$OUT/logs"
echo "done at $(( $(date +%s) - T0 )) s"
