"""Where one bench run's wall time goes, and what glibc's allocator costs (a script, not a test).

    python studies/bench_run_time.py [--scene lego] [--method flip+u] [--config 2] [--threads 1]

Each measurement is a fresh process, as a bench worker is, with one torch thread (the bench runs two
at once on the 2-core machine): importing flipviz and torch, loading the scene, building the run
(its plane estimate apart), the training steps, and the rest of `run()` (evaluation of the 8
unobserved views, checkpoint, renders and metrics files), after one import to warm the page cache.
Twice: with flipviz's allocator setting
(flipviz/runtime.py) and with glibc's defaults (FLIPVIZ_GLIBC_MALLOC=default). Run it on an idle machine.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))


@dataclass
class Args:
    scene: str = "lego"
    method: str = "flip+u"
    config: int = 2
    res: int = 100
    steps: int = 600
    threads: int = 1
    child: bool = False
    """Internal: measure one run in this process and print its phases as JSON."""
    out: Path = ROOT / "docs/results/run_time"


def measure(args: Args) -> dict:
    t0 = time.perf_counter()
    import torch

    from flipviz.training.config import TrainConfig
    from flipviz.training.setup import load_scene_for
    from flipviz.training.trainer import Trainer

    torch.set_num_threads(args.threads)
    t_import = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        data = {"data": LEGO} if args.scene == "lego" else {}
        cfg = TrainConfig.from_settings(
            scene=args.scene,
            method=args.method,
            config=args.config,
            res=args.res,
            steps=args.steps,
            no_rrd=True,
            images_every=0,
            out=Path(tmp) / "run",
            **data,
        )
        t = time.perf_counter()
        scene = load_scene_for(cfg)
        t_scene = time.perf_counter() - t
        t = time.perf_counter()
        trainer = Trainer(cfg, scene)
        t_build = time.perf_counter() - t
        est = trainer.plane_estimate.seconds if trainer.plane_estimate is not None else 0.0
        t = time.perf_counter()
        m = trainer.run()
        t_run = time.perf_counter() - t
    return {
        "import": t_import,
        "scene": t_scene,
        "plane estimate": est,
        "setup": t_build - est,
        "training": trainer.train_seconds,
        "evaluation and files": t_run - trainer.train_seconds,
        "total": time.perf_counter() - t0,
        "psnr": m["psnr"],
    }


def main(args: Args) -> None:
    if args.child:
        print(json.dumps(measure(args)))
        return
    from flipviz.files import write_json, write_text

    cmd = [
        sys.executable,
        __file__,
        "--child",
        "--scene",
        args.scene,
        "--method",
        args.method,
        "--config",
        str(args.config),
        "--res",
        str(args.res),
        "--steps",
        str(args.steps),
        "--threads",
        str(args.threads),
    ]
    subprocess.run([sys.executable, "-c", "import flipviz.training.trainer"], check=True)  # warm the page cache
    res = {}
    for mode in ("flipviz", "default"):
        env = dict(os.environ, FLIPVIZ_GLIBC_MALLOC=mode)
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
        res[mode] = json.loads(out.strip().splitlines()[-1])
        print(mode, res[mode], flush=True)
    phases = [k for k in res["flipviz"] if k != "psnr"]
    lines = [
        "# Where a bench run's wall time goes",
        "",
        f"`python studies/bench_run_time.py --scene {args.scene} --method {args.method} --config {args.config}`: "
        f"{args.res} px, {args.steps} steps, {args.threads} torch thread(s), "
        "a fresh process each, idle 2-core machine.",
        "",
        "| phase (s) | flipviz's allocator setting | glibc's defaults |",
        "|---|---|---|",
    ]
    lines += [f"| {k} | {res['flipviz'][k]:.1f} | {res['default'][k]:.1f} |" for k in phases]
    lines += [f"| PSNR (dB) | {res['flipviz']['psnr']:.2f} | {res['default']['psnr']:.2f} |"]
    write_json(args.out / "results.json", res)
    write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
