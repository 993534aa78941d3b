"""Engine benchmark (a script, not a test): is the grid engine fast enough to teach with?

For the built-in chair and the real lego (when --lego, $FLIPVIZ_LEGO or ../shared/data/nerf_synthetic/lego beside the
checkout exists) at 100 px, protocol configuration 1, method Flip+U:
  - seconds per training step,
  - seconds of training to reach the final unobserved-view PSNR within 0.5 dB,
  - render time of a 200x200 view,
and the same for the vanilla-NeRF field on a fixed time budget, side by side.
Targets: Flip+U within 0.5 dB of its final PSNR in <= 120 s; 200x200 render <= 250 ms;
>= 50x faster than vanilla NeRF to the same PSNR.

    python studies/bench_engine.py [--steps 1500] [--nerf-seconds 300] [--scenes chair,lego]

Timings on a shared CPU are noisy (20% or more): run it on an idle machine.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from flipviz.training.config import TrainConfig
from flipviz.training.events import ImagesEvent, Observer
from flipviz.training.trainer import Trainer

LEGO = Path(os.environ.get("FLIPVIZ_LEGO", Path(__file__).resolve().parents[2] / "shared/data/nerf_synthetic/lego"))


class Curve(Observer):
    """(train seconds, step, unobserved-view PSNR) at every ImagesEvent."""

    def __init__(self, trainer: Trainer, seconds: float | None = None):
        self.trainer, self.seconds, self.points = trainer, seconds, []

    def on_images(self, e: ImagesEvent) -> None:
        self.points.append((self.trainer.train_seconds, e.step, e.scalars.get("test_psnr", float("nan"))))

    def on_step(self, e) -> None:
        if self.seconds is not None and e.elapsed_s > self.seconds:
            self.trainer.stop()


def time_to_within(points: list[tuple[float, int, float]], final: float, tol: float = 0.5) -> tuple[float, int]:
    """First (seconds, step) at which the test PSNR is within `tol` dB of `final`."""
    for t, s, p in points:
        if p >= final - tol:
            return t, s
    return float("nan"), -1


def render_ms(trainer: Trainer, size: int = 200, repeats: int = 3) -> float:
    cam = trainer.split.tests[0].camera.resized(size)
    trainer.render(cam, ("rgb",))  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        trainer.render(cam, ("rgb", "depth", "opacity", "beta2"))
    return (time.perf_counter() - t0) / repeats * 1000.0


def run_curve(cfg: TrainConfig, eval_every: int, seconds: float | None = None) -> dict:
    cfg = cfg.with_settings(images_every=eval_every, checkpoint_every=0, log_every=10)
    tr = Trainer(cfg)
    curve = Curve(tr, seconds)
    tr.add_observer(curve)
    m = tr.run()
    final = m["psnr"]
    points = curve.points
    if not points or points[-1][1] != tr.step:  # make sure the final value is on the curve
        points.append((tr.train_seconds, tr.step, final))
    t_conv, s_conv = time_to_within(points, final)
    return {
        "field": cfg.engine.field,
        "scene": m["scene"],
        "method": cfg.method,
        "steps": tr.step,
        "final_psnr": final,
        "ssim": m["ssim"],
        "train_seconds": tr.train_seconds,
        "s_per_step": tr.train_seconds / max(tr.step, 1),
        "seconds_to_final_0.5dB": t_conv,
        "step_to_final_0.5dB": s_conv,
        "render_200_ms": render_ms(tr),
        "curve": [(round(t, 1), s, round(p, 2)) for t, s, p in points],
    }


@dataclass
class Args:
    """Engine benchmark: grid Flip+U against vanilla NeRF."""

    scenes: str = "chair,lego"
    lego: Path = LEGO
    steps: int | None = None
    """Grid steps (default: TrainConfig.steps)."""
    eval_every: int = 100
    nerf_seconds: float = 300.0
    """Vanilla NeRF time budget."""
    nerf_eval_every: int = 25
    res: int = 100
    out: Path | None = None


def main(args: Args) -> None:
    os.environ.setdefault("FLIPVIZ_CACHE", str(Path(tempfile.gettempdir()) / "flipviz-bench-cache"))
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_engine_"))
    rows = []
    for name in args.scenes.split(","):
        data = None
        if name == "lego":
            if not args.lego.is_dir():
                print(f"skip lego: {args.lego} not found")
                continue
            data = args.lego
        base = TrainConfig.from_settings(scene=name, data=data, method="flip+u", res=args.res, out=out / f"{name}-grid")
        if args.steps:
            base = base.with_settings(steps=args.steps)
        g = run_curve(base, args.eval_every)
        nerf_cfg = base.with_settings(field="nerf", out=out / f"{name}-nerf", steps=100000, batch_rays=1024)
        n = run_curve(nerf_cfg, args.nerf_eval_every, seconds=args.nerf_seconds)
        t_same, _ = time_to_within(n["curve"], g["final_psnr"], tol=0.0)
        speedup = (t_same / g["seconds_to_final_0.5dB"]) if np.isfinite(t_same) else None
        lower = n["train_seconds"] / g["seconds_to_final_0.5dB"]
        # The other way round: when did the grid first reach the NeRF's final PSNR (at its eval points)?
        t_grid_at_nerf, _ = time_to_within(g["curve"], n["final_psnr"], tol=0.0)
        for r in (g, n):
            rows.append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "curve"}))
        print(
            f"{name}: grid Flip+U {g['final_psnr']:.2f} dB, within 0.5 dB after {g['seconds_to_final_0.5dB']:.0f} s "
            f"({g['s_per_step'] * 1000:.0f} ms/step), 200x200 render {g['render_200_ms']:.0f} ms | vanilla NeRF "
            f"{n['final_psnr']:.2f} dB after {n['train_seconds']:.0f} s ({n['s_per_step']:.2f} s/step), render "
            f"{n['render_200_ms']:.0f} ms | speed-up to the same PSNR: "
            + (f"{speedup:.0f}x" if speedup else f">= {lower:.0f}x (NeRF never reached {g['final_psnr']:.2f} dB)")
            + f"; the grid passed the NeRF's final {n['final_psnr']:.2f} dB by {t_grid_at_nerf:.1f} s "
            f"({n['train_seconds'] / t_grid_at_nerf:.0f}x)"
        )
    (out / "bench_engine.json").write_text(json.dumps(rows, indent=1))
    print(f"results: {out / 'bench_engine.json'}")


if __name__ == "__main__":
    main(tyro.cli(Args))
