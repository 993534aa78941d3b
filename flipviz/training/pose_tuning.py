"""The released code's evaluation (minjae-lulu/Just-Flip, BARF's `evaluate_full` with `test_photo`): each
test pose is brought into the run's refined frame and tuned on its own ground truth before it is scored.

It looks at the test image, so it is not flipviz's protocol; it is the authors' (`--eval-tune-steps 100`),
and every table that uses it says so. Two steps, as the released code takes them:

1. Alignment (`model/barf.py: prealign_cameras`). When BA moved the inputs too (`--refine all`) the world
   frame drifts; the similarity that takes the mirrored cameras' initial centres to their refined ones
   (Procrustes: translation, scale, rotation) maps each test camera into the refined frame:

       c' = s1 R^T (c - t0) / s0 + t1,    R_c2w' = R^T R_c2w

   With the inputs fixed (flipviz: `--refine mirrored`, or no BA) they anchor the frame: no alignment.
2. Tuning (`evaluate_test_time_photometric_optim`): a correction xi in se(3) of the test camera,
   c2w = c2w_aligned Exp(xi) (on the camera side, as pose_refine.py), starts at 0 and takes
   `steps` Adam steps (lr 1e-3, no schedule) on the MSE of 1024 random pixels of the test image.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pypose as pp
import torch

from flipviz.data.cameras import Camera, View, rays_from_c2w
from flipviz.model import RadianceModel

TUNE_LR = 1e-3  # options/barf_blender.yaml: optim.lr_pose (test_iter uses it without a schedule)
TUNE_RAYS = 1024  # options/nerf_blender.yaml: nerf.rand_rays


@dataclass(frozen=True)
class Similarity:
    """x -> s1 R^T (x - t0) / s0 + t1: the initial frame to the refined one (BARF's procrustes_analysis)."""

    t0: np.ndarray
    t1: np.ndarray
    s0: float
    s1: float
    R: np.ndarray

    @classmethod
    def between(cls, initial: np.ndarray, refined: np.ndarray) -> Similarity:
        """From camera centres (N, 3) before and after BA; identity for fewer than 3 or a degenerate set."""
        if len(initial) < 3:
            return cls.identity()
        t0, t1 = initial.mean(0), refined.mean(0)
        a, b = initial - t0, refined - t1
        s0, s1 = float(np.sqrt((a**2).sum(-1).mean())), float(np.sqrt((b**2).sum(-1).mean()))
        if s0 < 1e-9 or s1 < 1e-9:
            return cls.identity()
        U, _, Vt = np.linalg.svd((a / s0).T @ (b / s1))
        R = U @ Vt
        if np.linalg.det(R) < 0:
            R[2] *= -1
        return cls(t0, t1, s0, s1, R)

    @classmethod
    def identity(cls) -> Similarity:
        return cls(np.zeros(3), np.zeros(3), 1.0, 1.0, np.eye(3))

    def camera(self, c2w: np.ndarray) -> np.ndarray:
        """A camera-to-world pose (4, 4) of the initial frame, in the refined one."""
        out = np.array(c2w, dtype=np.float64)
        out[:3, 3] = self.s1 * (self.R.T @ (out[:3, 3] - self.t0)) / self.s0 + self.t1
        out[:3, :3] = self.R.T @ out[:3, :3]
        return out


def tune_pose(
    model: RadianceModel, camera: Camera, image: np.ndarray, steps: int, generator: torch.Generator
) -> np.ndarray:
    """The pose (4, 4) of `camera` after `steps` Adam steps on the MSE of TUNE_RAYS random pixels of its
    ground truth `image` (H, W, 3) a step; the field is not changed."""
    dev = model.device
    c2w = torch.as_tensor(camera.c2w, dtype=torch.float32, device=dev)
    if steps <= 0:
        return camera.c2w
    _, dirs = (torch.from_numpy(a).to(dev) for a in camera.rays())
    dirs_cam = dirs @ c2w[:3, :3]  # (HW, 3) each pixel's direction in the camera frame
    target = torch.as_tensor(image, dtype=torch.float32, device=dev).reshape(-1, 3)
    xi = torch.zeros(6, device=dev, requires_grad=True)  # se(3): [t, r], pypose's order
    opt = torch.optim.Adam([xi], lr=TUNE_LR)
    frozen = [p for p in model.parameters() if p.requires_grad]
    for p in frozen:  # only the pose learns: no gradient reaches the field
        p.requires_grad_(False)
    try:
        for _ in range(steps):
            pick = torch.randperm(len(target), generator=generator)[:TUNE_RAYS].to(dev)
            pose = c2w @ pp.se3(xi).Exp().matrix()
            o, d = rays_from_c2w(pose, dirs_cam.index_select(0, pick))
            loss = (model.render_rays(o, d, training=False)["rgb"] - target.index_select(0, pick)).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    finally:
        for p in frozen:
            p.requires_grad_(True)
    with torch.no_grad():
        return (c2w @ pp.se3(xi).Exp().matrix()).double().cpu().numpy()


def test_alignment(refined_inputs: bool, initial: list[Camera], refined: np.ndarray | None) -> Similarity:
    """The similarity that brings test cameras into the run's frame: the mirrored cameras' initial centres
    to their refined ones when BA moved the inputs too (the released code's prealign_cameras); else the
    inputs anchor the frame: the identity."""
    if not refined_inputs or refined is None or not initial:
        return Similarity.identity()
    return Similarity.between(np.stack([c.center for c in initial]), np.asarray(refined)[:, :3, 3])


def eval_renders(
    render: Callable[[Camera], dict[str, np.ndarray]],
    model: RadianceModel,
    views: list[View],
    steps: int,
    align: Similarity,
    seed: int,
) -> list[dict[str, np.ndarray]]:
    """`render` of each view: at its pose, or, with `steps` > 0, at its pose aligned by `align` and tuned on
    its ground truth (the authors' protocol)."""
    if steps <= 0:
        return [render(v.camera) for v in views]
    generator = torch.Generator().manual_seed(seed)  # the pixels each step tunes on
    out = []
    for v in views:
        aligned = v.camera.with_pose(align.camera(v.camera.c2w))
        out.append(render(aligned.with_pose(tune_pose(model, aligned, v.rgb, steps, generator))))
    return out
