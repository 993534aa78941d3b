"""Fit a radiance model to posed views: the minimal loop, photometric MSE only.

The full training loop of the five methods (uncertainty, events, checkpoints) is
`flipviz.training.trainer`; this one is the model API in its simplest use (field benchmark,
model tests): random rays from all views, MSE + the field's regulariser, and, with a
`PoseRefiner`, BARF refinement of the poses.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from flipviz.data.cameras import View, rays_from_c2w
from flipviz.data.rays import RayBank
from flipviz.model.objective import Objective, psnr
from flipviz.model.pose_refine import PoseRefiner
from flipviz.model.radiance import RadianceModel


def fit(
    model: RadianceModel,
    views: list[View],
    steps: int,
    batch_rays: int = 4096,
    refiner: PoseRefiner | None = None,
    seconds: float | None = None,
    seed: int = 0,
    callback: Callable[[int, float], None] | None = None,
) -> dict:
    """Optimise `model` (and the refiner's poses) on `views`; stops after `steps` or `seconds`.

    callback(step, elapsed_s) is called after every step (for PSNR-vs-time curves).
    Returns {"steps", "seconds", "loss"} (the last batch loss).
    """
    bank = RayBank.from_images([v.camera for v in views], [v.rgb for v in views], model.device)
    c2w = torch.as_tensor(np.stack([v.camera.c2w for v in views]), dtype=torch.float32, device=model.device)
    gen = torch.Generator().manual_seed(seed)
    mse = Objective()  # no uncertain rays: the photometric MSE
    certain = torch.zeros(batch_rays, dtype=torch.bool, device=model.device)
    opt = model.make_optimizer()
    popt = refiner.make_optimizer() if refiner is not None else None
    t0 = time.perf_counter()
    loss = torch.zeros(())
    step = 0
    for step in range(steps):
        if model.update_schedule(step, steps):
            opt = model.make_optimizer()
        model.adjust_lr(opt, step, steps)
        idx = bank.sample(batch_rays, gen)
        poses = refiner() if refiner is not None else c2w  # (V, 4, 4)
        o, d = rays_from_c2w(poses[bank.view[idx]], bank.dirs_cam[idx])
        out = model.render_rays(o, d, training=True)
        loss = mse(out, bank.rgb[idx], certain, step) + model.regulariser()
        opt.zero_grad(set_to_none=True)
        if popt is not None:
            refiner.adjust_lr(popt, step)
            popt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if popt is not None:
            popt.step()
        elapsed = time.perf_counter() - t0
        if callback is not None:
            callback(step + 1, elapsed)
        if seconds is not None and elapsed > seconds:
            break
    return {"steps": step + 1, "seconds": time.perf_counter() - t0, "loss": float(loss.detach())}


def image_psnr(model: RadianceModel, views: list[View]) -> float:
    """Mean PSNR (dB) of full renders against the views' images."""
    return float(np.mean([psnr(np.mean((model.render_image(v.camera)["rgb"] - v.rgb) ** 2)) for v in views]))
