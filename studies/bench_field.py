"""Field benchmark (a script, not a test): speed and held-out PSNR of the grid and NeRF fields.

    python studies/bench_field.py --seconds 120 --fields grid nerf-small nerf

Scene: the built-in chair, its 16 ring views at --res px; trains on 12, tests on the 4 views
at ring positions 1, 5, 9, 13. Prints seconds per step, rays/s, full-render time at 100 and
200 px, and held-out PSNR at the checkpoints. Timings depend on the machine's load.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import tyro

from flipviz.data.builtin import load_builtin
from flipviz.data.protocol import RING_INDICES
from flipviz.model import GridConfig, ModelConfig, NerfConfig, RadianceModel
from flipviz.model.fit import fit, image_psnr

CONFIGS = {
    "grid": (ModelConfig(GridConfig(), n_samples=64), 4096),
    "nerf-small": (ModelConfig(NerfConfig(depth=4, width=128), n_samples=64), 1024),
    "nerf": (ModelConfig(NerfConfig(), n_samples=128), 1024),  # the paper's 8x256, PE 10/4, 128 samples
}


def render_time(model: RadianceModel, cam, res: int) -> float:
    """Best of 3 full renders (one, when it takes over 2 s)."""
    c = cam.resized(res)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        model.render_image(c)
        times.append(time.perf_counter() - t)
        if times[-1] > 2.0:
            break
    return min(times)


@dataclass
class Args:
    """Field benchmark: speed and held-out PSNR of the grid and NeRF fields."""

    fields: tuple[Literal["grid", "nerf-small", "nerf"], ...] = ("grid", "nerf-small")
    res: int = 100
    seconds: float = 120.0
    """Training wall-clock budget per field."""
    steps: int = 3000
    """Schedule length (training stops at --seconds)."""
    checkpoints: tuple[float, ...] = (30, 60, 120, 300)
    threads: int = 1
    """Torch threads (1 is far faster when the 2 cores are oversubscribed)."""


def main(args: Args) -> None:
    torch.set_num_threads(args.threads)
    scene = load_builtin("chair", res=args.res)
    ring = [scene.views[i] for i in RING_INDICES]
    test = ring[1::4]
    train = [v for k, v in enumerate(ring) if k % 4 != 1]
    print(
        f"chair {args.res}px: {len(train)} train / {len(test)} test views, {torch.get_num_threads()} threads, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    for name in args.fields:
        cfg, rays = CONFIGS[name]
        torch.manual_seed(0)
        model = RadianceModel(cfg, scene.bbox, scene.near, scene.far, False, "cpu")
        marks = sorted(c for c in args.checkpoints if c <= args.seconds) or [args.seconds]
        results: list[tuple[float, int, float]] = []
        paused = [0.0]  # time spent evaluating, excluded from the training clock
        step_times: list[float] = []
        last = [0.0]

        def cb(step: int, elapsed: float) -> None:
            step_times.append(elapsed - last[0])
            last[0] = elapsed
            if marks and elapsed - paused[0] >= marks[0]:
                t = time.perf_counter()
                results.append((elapsed - paused[0], step, image_psnr(model, test)))
                marks.pop(0)
                paused[0] += time.perf_counter() - t
                last[0] += time.perf_counter() - t

        r = fit(model, train, steps=args.steps, batch_rays=rays, seconds=args.seconds, callback=cb)
        if not results or results[-1][1] != r["steps"]:
            results.append((r["seconds"] - paused[0], r["steps"], image_psnr(model, test)))
        tail = step_times[len(step_times) // 2 :] or step_times
        sec = float(np.median(tail))
        r100 = render_time(model, test[0].camera, 100)
        r200 = render_time(model, test[0].camera, 200)
        print(
            f"\n[{name}] {rays} rays/step, median step (second half) {sec * 1000:.0f} ms, "
            f"{rays / sec:.0f} rays/s; steps done {r['steps']}; resolution {getattr(model.field, 'resolution', '-')}"
        )
        print(f"  render 100px {r100 * 1000:.0f} ms, 200px {r200 * 1000:.0f} ms")
        for el, step, p in results:
            print(f"  held-out PSNR after {el:.0f} s of training (step {step}): {p:.2f} dB")


if __name__ == "__main__":
    main(tyro.cli(Args))
