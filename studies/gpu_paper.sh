#!/usr/bin/env bash
# The paper's setting on a GPU: B/L and Flip+U on lego, configuration 1, with `--preset paper`
# (vanilla NeRF, 128 samples, lr 5e-4 -> 1e-4, the NLL from 10k of 50k steps), each trained for
# SECONDS of wall time (a graceful stop: the run keeps its checkpoint and is evaluated), then PSNR
# and steps/s of both written to $OUT/summary.json and printed.
#
#   bash studies/gpu_paper.sh                      # about 10 minutes on one GPU
#   DEVICE=cpu SECONDS_PER_RUN=60 STEPS=2 BATCH=64 RES=16 bash studies/gpu_paper.sh   # the CPU check (tests)
#
# Settings (environment): DEVICE (cuda), SECONDS_PER_RUN (270), STEPS (50000: the schedule's length;
# the run stops at SECONDS_PER_RUN or STEPS), BATCH (1024 rays), RES (200: lego's own width),
# LEGO (../shared/data/nerf_synthetic/lego), OUT (gpu_paper_out), PYTHON (.venv/bin/python).
set -euo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
SECONDS_PER_RUN=${SECONDS_PER_RUN:-270}
STEPS=${STEPS:-50000}
BATCH=${BATCH:-1024}
RES=${RES:-200}
LEGO=${LEGO:-../shared/data/nerf_synthetic/lego}
OUT=${OUT:-gpu_paper_out}
PYTHON=${PYTHON:-.venv/bin/python}

for method in bl flip+u; do
  dir="$OUT/lego-${method//+/_}"
  rm -rf "$dir"
  # SIGINT after SECONDS_PER_RUN: flipviz stops after the step, saves the checkpoint, evaluates (exit 130)
  timeout -s INT -k 600 "$SECONDS_PER_RUN" "$PYTHON" -m flipviz.cli train --data "$LEGO" --preset paper \
    --method "$method" --config 1 --res "$RES" --steps "$STEPS" --batch-rays "$BATCH" --device "$DEVICE" \
    --mirror-plane official --log-every 100 --images-every 0 --checkpoint-every 5000 --no-rrd --out "$dir" || true
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
                 "ssim": round(m["ssim"], 4), "iou": round(m.get("iou", float("nan")), 4), "train_seconds": round(m["train_seconds"], 1)})
summary = {"device": device, "scene": "lego", "config": 1, "preset": "paper", "runs": rows}
(out / "summary.json").write_text(json.dumps(summary, indent=2))
for r in rows:
    print(f"{r['method']:>7}: {r['steps']} steps ({r['steps_per_s']} steps/s), PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.3f}, IoU {r['iou']:.3f}")
EOF
