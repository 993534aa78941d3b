"""What Just Flip adds to a NeRF training step (paper Sec. IV), in one place.

A plain NeRF step (`Trainer._train_step`): draw random pixels of the training views, cast their
rays from the views' poses, render them, and minimise the squared error plus the field's
regulariser. Just Flip changes three things, one function each:

1. `mirrored_views`: more training views. Each input image is flipped left-right and posed
   (geometry/mirror.py) by the paper's rule (`--mirror-pose lookat`: reflect its camera centre
   through a plane through the centre of the least-squares sphere of the input centres, put it
   back on the sphere, look at the sphere's centre) or, by default, by reflecting the whole camera
   through the plane (`reflect`: the same on the paper's ring, exact for any plane and trajectory).
2. `pose_refiner`: those poses are only estimates, so they become parameters (bundle adjustment,
   model/pose_refine.py): c2w = c2w_init @ Exp(xi) for the mirrored cameras; inputs stay fixed.
3. `objective`: a flipped image is a true view only of a symmetric object, so the mirrored rays
   get a learned variance beta^2 and, after a warm-up, the Gaussian NLL (model/objective.py):
   mirrored pixels that contradict the real views are down-weighted.

Which method uses which is `methods.py` (B/L+U uses 3 on the input rays; Upper uses none).
"""

from __future__ import annotations

import numpy as np
import torch

from flipviz.data.cameras import Camera, View
from flipviz.data.dataset import Plane, SceneData
from flipviz.geometry.mirror import MirrorSet, make_mirror_set
from flipviz.model.objective import Objective
from flipviz.model.pose_refine import PoseRefiner
from flipviz.model.renderer import ray_box
from flipviz.training.config import TrainConfig
from flipviz.training.methods import MethodSpec, TrainingSet, TrainView


def mirrored_views(cfg: TrainConfig, inputs: list[View], scene: SceneData, estimated: Plane | None = None) -> MirrorSet:
    """1. The flipped inputs with their initial poses (and the exact ones, when the scene's plane is
    known), for cfg.mirror_plane; for "auto", the `estimated` plane (plane_estimate.py)."""
    plane: str | Plane = cfg.mirror_plane
    if plane == "auto":
        plane = estimated if estimated is not None else "opposite"  # no estimate for methods without mirrors
    return make_mirror_set(inputs, plane, scene.symmetry_plane, scene.center, scene.up, cfg.mirror_pose)


def mirrored_train_views(spec: MethodSpec, mirrors: MirrorSet, bbox: np.ndarray) -> list[TrainView]:
    """The mirrored views as training views: refined when BA is on, uncertain under Flip+U. A view
    without a mask (a capture's background) keeps only the rays through the scene box `bbox`: a
    flipped background is not what the mirrored camera would see."""
    return [
        TrainView("mirror", v.camera, v.rgb, spec.ba, spec.uncertain_mirrors, v.meta.get("source", ""),
                  None if v.alpha is not None else rays_through_box(v.camera, bbox))  # fmt: skip
        for v in mirrors.views
    ]


def rays_through_box(camera: Camera, bbox: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose rays cross the box (2, 3) in front of the camera."""
    o, d = (torch.from_numpy(a) for a in camera.rays())
    t_in, t_out = ray_box(o, d, torch.as_tensor(bbox, dtype=torch.float32))
    return ((t_out > t_in) & (t_out > 0)).numpy().reshape(camera.height, camera.width)


def pose_refiner(ts: TrainingSet, steps: int, device: torch.device | str) -> PoseRefiner | None:
    """2. BA of the views whose refine flag is set (the mirrored ones); None when no pose moves."""
    if not bool(ts.refine_mask.any()):
        return None
    return PoseRefiner(ts.init_c2w, ts.refine_mask, steps, device=device)


def objective(cfg: TrainConfig, beta_min: float) -> Objective:
    """3. MSE for the first `uncertainty_start` of the steps, then the NLL on uncertain rays."""
    return Objective(beta_min, cfg.density_weight, nll_start=int(cfg.uncertainty_start * cfg.steps))
