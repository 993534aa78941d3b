"""What the remaining speed levers of a grid run would cost in quality (a script, not a test).

    python studies/bench_speed_levers.py [--config 1] [--workers 2]

The bench's steps are what is left of its wall time (README, Bench speed). Three settings of the
grid field decide how much work a step does, and each changes what a run computes:
- `color_thresh`: colour is evaluated only where a sample's weight exceeds it (default 1e-4);
- `occ_start`: the step of the first occupancy refresh (default 100; before it, every sample of
  every ray is evaluated);
- both.
Each lever trains lego's B/L and Upper (configuration --config, 100 px, 600 steps, the bench's
settings, one thread a run, --workers runs at a time) and is scored on **held-out views that the
protocol never uses**: the second turn of the test orbit (indices 100-199, every fifth), 20 to 47
degrees of elevation, never an input, test or Upper view. The unobserved test views are not looked
at, so nothing here is tuned on them. Writes docs/results/speed_levers/.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))
HELD_OUT = tuple(range(100, 200, 5))  # the orbit's second turn: no protocol view is there
LEVERS: dict[str, dict] = {
    "defaults": {},
    "color_thresh 1e-3": {"color_thresh": 1e-3},
    "occ_start 50": {"occ_start": 50},
    "both": {"color_thresh": 1e-3, "occ_start": 50},
}


@dataclass
class Args:
    config: int = 1
    methods: tuple[str, ...] = ("bl", "upper")
    workers: int = 2
    out: Path = ROOT / "docs/results/speed_levers"


def train_one(job: tuple[str, str, int]) -> dict:
    """Train one (lever, method) run in this process; its training time and held-out PSNR."""
    import tempfile

    import numpy as np
    import torch

    from flipviz.training.config import TrainConfig
    from flipviz.training.evaluate import image_psnr
    from flipviz.training.setup import load_scene_for
    from flipviz.training.trainer import Trainer

    lever, method, config = job
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig.from_settings(
            scene="lego",
            data=LEGO,
            method=method,
            config=config,
            res=100,
            no_rrd=True,
            images_every=0,
            checkpoint_every=0,
            out=Path(tmp) / "run",
        )
        scene = load_scene_for(cfg)
        trainer = Trainer(cfg, scene)
        field = trainer.model.field
        field.cfg = replace(field.cfg, **LEVERS[lever])  # read by the field's schedule at every step, from step 0
        trainer.run()  # its test-view scores are not read here
        views = [scene.views[i] for i in HELD_OUT]
        psnrs = [image_psnr(trainer.render(v.camera, ("rgb",))["rgb"], v.rgb) for v in views]
    return {
        "lever": lever,
        "method": method,
        "config": config,
        "train_seconds": trainer.train_seconds,
        "held_out_psnr": float(np.mean(psnrs)),
    }


def main(args: Args) -> None:
    from flipviz.files import write_json, write_text

    jobs = [(lever, m, args.config) for m in args.methods for lever in LEVERS]
    import multiprocessing as mp

    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(train_one, jobs))
    base = {r["method"]: r for r in rows if r["lever"] == "defaults"}
    lines = [
        "# Speed levers of the grid field: time against held-out quality",
        "",
        f"`python studies/bench_speed_levers.py --config {args.config}`: lego, configuration {args.config}, "
        f"100 px, 600 steps of 1024 rays, 64 samples, {args.workers} runs at a time with one thread each, on the "
        "2-core machine. Held-out PSNR: the mean over 20 views of the orbit's second turn (indices 100-195, "
        "every fifth), which the protocol never uses; the unobserved test views are not looked at.",
        "",
        "| method | lever | training (s) | speed-up | held-out PSNR (dB) | change (dB) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        b = base[r["method"]]
        lines.append(
            f"| {r['method']} | {r['lever']} | {r['train_seconds']:.1f} | "
            f"{b['train_seconds'] / r['train_seconds']:.2f}x "
            f"| {r['held_out_psnr']:.2f} | {r['held_out_psnr'] - b['held_out_psnr']:+.2f} |"
        )
    write_json(args.out / "results.json", {"args": {**vars(args), "out": str(args.out)}, "rows": rows})
    write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(json.dumps(rows))


if __name__ == "__main__":
    main(tyro.cli(Args))
