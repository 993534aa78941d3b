"""A minimal training loop over posed views: for the model's tests and benchmark only.

The real loop (methods, events, uncertainty, checkpoints) is flipviz.training.trainer; this one
shows the model API in its simplest use: random rays from all views, photometric MSE + the
field's regulariser, optional BARF refinement of the poses.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from flipviz.data.cameras import View, pixel_directions, rays_from_c2w
from flipviz.model import RadianceModel
from flipviz.model.losses import photometric_mse, psnr
from flipviz.model.pose_refine import PoseRefiner


class RayBank:
    """All pixels of a list of views: camera index, camera-frame direction and colour per pixel."""

    def __init__(self, views: list[View], device: torch.device | str = "cpu"):
        cams, dirs, rgbs = [], [], []
        for i, v in enumerate(views):
            c = v.camera
            dirs.append(pixel_directions(c.width, c.height, c.focal))
            rgbs.append(v.rgb.reshape(-1, 3))
            cams.append(np.full(c.width * c.height, i))
        self.cam = torch.as_tensor(np.concatenate(cams), device=device)
        self.dirs = torch.as_tensor(np.concatenate(dirs), dtype=torch.float32, device=device)
        self.rgb = torch.as_tensor(np.concatenate(rgbs), dtype=torch.float32, device=device)
        self.c2w = torch.as_tensor(np.stack([v.camera.c2w for v in views]), dtype=torch.float32, device=device)

    def batch(self, n: int, gen: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        idx = torch.randint(0, self.rgb.shape[0], (n,), generator=gen, device=self.rgb.device)
        return self.cam[idx], self.dirs[idx], self.rgb[idx]


def fit(
    model: RadianceModel,
    views: list[View],
    steps: int,
    batch_rays: int = 4096,
    refiner: PoseRefiner | None = None,
    seconds: float | None = None,
    seed: int = 0,
    callback=None,
) -> dict:
    """Optimise `model` (and the refiner's poses) on `views`; stops after `steps` or `seconds`.

    callback(step, elapsed_s) is called after every step (for PSNR-vs-time curves).
    Returns {"steps", "seconds", "loss"} (last batch loss).
    """
    bank = RayBank(views, model.device)
    gen = torch.Generator(device=model.device).manual_seed(seed)
    opt = model.make_optimizer(steps)
    popt = refiner.make_optimizer() if refiner is not None else None
    t0 = time.perf_counter()
    loss = torch.zeros(())
    step = 0
    for step in range(steps):
        if model.update_schedule(step, steps):
            opt = model.make_optimizer(steps)
        model.adjust_lr(opt, step, steps)
        cam, dirs, target = bank.batch(batch_rays, gen)
        c2w = refiner()[cam] if refiner is not None else bank.c2w[cam]
        o, d = rays_from_c2w(c2w, dirs)
        out = model.render_rays(o, d, training=True)
        loss = photometric_mse(out["rgb"], target) + model.regulariser()
        opt.zero_grad(set_to_none=True)
        if popt is not None:
            refiner.adjust_lr(popt, step)  # type: ignore[union-attr]
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
    vals = []
    for v in views:
        out = model.render_image(v.camera)
        vals.append(psnr(np.mean((out["rgb"] - v.rgb) ** 2)))
    return float(np.mean(vals))
