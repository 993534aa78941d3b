#!/usr/bin/env bash
# The paper's setting on a GPU, toward Table III's 50k steps (issue 40): B/L, B/L+U and Flip+U on lego,
# configuration 1, with `--preset paper` (vanilla NeRF, 128 samples, lr 5e-4 -> 1e-4, the NLL from 10k of
# 50k steps) and the official plane x = 0. Each run trains for SECONDS_PER_RUN of wall time (a graceful
# stop: the run keeps its checkpoint and is scored in the authors' protocol), and the next call resumes it
# from that checkpoint: device time lent in short sessions adds up. A run that reached STEPS is skipped.
# PSNR, steps and steps/s of each go to $OUT/summary.json and are printed.
#
#   bash studies/gpu_paper.sh                      # about 3 x 4.5 minutes on one GPU; again: resume
#   DEVICE=cpu SECONDS_PER_RUN=60 STEPS=2 BATCH=64 RES=16 EVAL="..." bash studies/gpu_paper.sh   # tests
#
# Settings (environment): DEVICE (cuda), SECONDS_PER_RUN (270), STEPS (50000: the schedule's length; the
# run stops at SECONDS_PER_RUN or STEPS), BATCH (1024 rays), RES (200: the lego orbit's own width),
# METHODS ("bl bl+u flip+u"), EVAL (the authors' protocol: every 4th orbit view the run did not train on,
# each pose tuned 100 steps on its ground truth), LEGO (../shared/data/nerf_synthetic/lego), OUT
# (gpu_paper_out), PYTHON (.venv/bin/python).
set -euo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
SECONDS_PER_RUN=${SECONDS_PER_RUN:-270}
STEPS=${STEPS:-50000}
BATCH=${BATCH:-1024}
RES=${RES:-200}
METHODS=${METHODS:-bl bl+u flip+u}
EVAL=${EVAL:---eval-views orbit --eval-tune-steps 100 --eval-every 4}
LEGO=${LEGO:-../shared/data/nerf_synthetic/lego}
OUT=${OUT:-gpu_paper_out}
PYTHON=${PYTHON:-.venv/bin/python}

steps_done() { # the steps a run folder's metrics.json says it trained (0 without one)
  "$PYTHON" -c 'import json, sys; print(json.load(open(sys.argv[1])).get("steps", 0))' "$1/metrics.json" 2>/dev/null || echo 0
}

for method in $METHODS; do
  dir="$OUT/lego-${method//+/_}"
  if [ "$(steps_done "$dir")" -ge "$STEPS" ]; then
    echo "gpu_paper: $method already trained $STEPS steps: skipped"
    continue
  fi
  start=(--out "$dir" --overwrite)
  if [ -f "$dir/checkpoint.pt" ]; then start=(--out "$dir" --resume "$dir"); fi
  # SIGINT after SECONDS_PER_RUN: flipviz stops after the step, saves the checkpoint, evaluates (exit 130)
  # shellcheck disable=SC2086  # EVAL is a list of options
  timeout -s INT -k 900 "$SECONDS_PER_RUN" "$PYTHON" -m flipviz.cli train --data "$LEGO" --preset paper \
    --method "$method" --config 1 --res "$RES" --steps "$STEPS" --batch-rays "$BATCH" --device "$DEVICE" \
    --mirror-plane official $EVAL --log-every 100 --images-every 0 --checkpoint-every 1000 --no-rrd \
    "${start[@]}" || true
  test -f "$dir/metrics.json" || { echo "gpu_paper: $method wrote no metrics.json" >&2; exit 1; }
done

"$PYTHON" - "$OUT" "$DEVICE" <<'EOF'
import json, sys
from pathlib import Path

out, device = Path(sys.argv[1]), sys.argv[2]
rows = []
for d in sorted(out.glob("lego-*")):
    m = json.loads((d / "metrics.json").read_text())
    rate = m["steps"] / m["train_seconds"] if m.get("train_seconds") else float("nan")
    rows.append({"method": m["method"], "steps": m["steps"], "steps_per_s": round(rate, 2), "psnr": round(m["psnr"], 3),
                 "ssim": round(m["ssim"], 4), "scored_views": m["scored_views"], "train_seconds": round(m["train_seconds"], 1)})
summary = {"device": device, "scene": "lego", "config": 1, "preset": "paper", "runs": rows}
(out / "summary.json").write_text(json.dumps(summary, indent=2))
for r in rows:
    print(f"{r['method']:>7}: {r['steps']} steps ({r['steps_per_s']} steps/s), PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.3f} on {r['scored_views']} views")
EOF
