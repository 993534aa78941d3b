"""Which views and which losses each of the five methods trains with (PROTOCOL.md, "Methods").

| method | trains on              | pose refinement (BA) | learned beta^2 on   |
|--------|------------------------|----------------------|---------------------|
| bl     | 8 inputs               | none                 | -                   |
| bl+u   | 8 inputs               | none                 | all input rays      |
| flip   | 8 inputs + 8 mirrors   | mirrored poses       | -                   |
| flip+u | 8 inputs + 8 mirrors   | mirrored poses       | mirrored rays       |
| upper  | 8 inputs + 8 upper     | none                 | -                   |

`cfg.ba = False` and `cfg.uncertainty = False` switch BA / beta^2 off (paper Table II ablation);
`cfg.refine = "all"` lets BA move the original input poses too.

The training set is a flat ray bank: per ray its camera index, camera-frame direction, target
colour and two flags. Ray origins and world directions are computed each step from the camera's
current pose, so refined poses receive gradients.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from flipviz.data.cameras import Camera, View, pixel_directions
from flipviz.training.config import METHODS, TrainConfig

ViewKind = Literal["input", "mirror", "upper"]


@dataclass(frozen=True)
class MethodSpec:
    name: str
    mirrors: bool  # add the 8 flipped images with their estimated poses
    upper: bool  # add the 8 Upper views (true images of the unobserved side)
    ba: bool  # refine poses (BARF-style); mirrored ones, plus inputs when refine_inputs
    refine_inputs: bool
    uncertain_inputs: bool  # learned beta^2 on input rays
    uncertain_mirrors: bool  # learned beta^2 on mirrored rays

    @property
    def uses_beta(self) -> bool:
        return self.uncertain_inputs or self.uncertain_mirrors


def method_spec(cfg: TrainConfig) -> MethodSpec:
    m = cfg.method
    if m not in METHODS:
        raise ValueError(f"unknown method {m!r}; choose one of {', '.join(METHODS)}")
    flip = m in ("flip", "flip+u")
    ba = flip and cfg.ba
    return MethodSpec(
        name=m,
        mirrors=flip,
        upper=m == "upper",
        ba=ba,
        refine_inputs=ba and cfg.refine == "all",
        uncertain_inputs=m == "bl+u" and cfg.uncertainty,
        uncertain_mirrors=m == "flip+u" and cfg.uncertainty,
    )


@dataclass
class TrainView:
    kind: ViewKind
    camera: Camera  # initial pose
    image: np.ndarray  # (H, W, 3) float32 target (the flipped image for mirrors)
    refine: bool  # pose is refined by BA
    uncertain: bool  # its rays use the learned-variance loss
    source: str = ""  # mirrors: the input view it was flipped from


@dataclass
class RayBank:
    """All training rays, flat. Tensors live on the training device."""

    cam: torch.Tensor  # (N,) long: index into TrainingSet.views
    dirs_cam: torch.Tensor  # (N, 3) float32 camera-frame directions (z = -1)
    rgb: torch.Tensor  # (N, 3) float32 targets
    mirrored: torch.Tensor  # (N,) bool
    uncertain: torch.Tensor  # (N,) bool

    def __len__(self) -> int:
        return int(self.cam.shape[0])

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """n random ray indices (with replacement), drawn on the CPU for reproducibility."""
        return torch.randint(0, len(self), (n,), generator=generator).to(self.cam.device)


@dataclass
class TrainingSet:
    spec: MethodSpec
    views: list[TrainView]
    bank: RayBank
    init_c2w: torch.Tensor  # (V, 4, 4) float32 initial poses of all training views
    refine_mask: torch.Tensor  # (V,) bool: which poses BA refines
    mirror_ids: list[int] = field(default_factory=list)  # indices of the mirrored views, in order

    @property
    def mirror_views(self) -> list[TrainView]:
        return [self.views[i] for i in self.mirror_ids]


def _view_rays(cam: Camera, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if image.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"view {cam.name!r}: image {image.shape[:2]} does not match camera {cam.height}x{cam.width}")
    return pixel_directions(cam.width, cam.height, cam.focal).astype(np.float32), image.reshape(-1, 3).astype(np.float32)


def build_training_set(
    cfg: TrainConfig,
    inputs: list[View],
    mirrors: list[View] | None = None,
    uppers: list[View] | None = None,
    device: str | torch.device = "cpu",
) -> TrainingSet:
    """The views, flags and ray bank of `cfg.method`; mirrors / uppers are used only when it needs them."""
    spec = method_spec(cfg)
    views = [TrainView("input", v.camera, v.rgb, spec.refine_inputs, spec.uncertain_inputs) for v in inputs]
    mirror_ids: list[int] = []
    if spec.mirrors:
        if not mirrors:
            raise ValueError(f"method {spec.name} needs the mirrored views")
        for v in mirrors:
            mirror_ids.append(len(views))
            views.append(TrainView("mirror", v.camera, v.rgb, spec.ba, spec.uncertain_mirrors, v.meta.get("source", "")))
    if spec.upper:
        if not uppers:
            raise ValueError("method upper needs the Upper views")
        views += [TrainView("upper", v.camera, v.rgb, False, False) for v in uppers]

    cams, dirs, rgbs, mir, unc = [], [], [], [], []
    for i, v in enumerate(views):
        d, c = _view_rays(v.camera, v.image)
        n = d.shape[0]
        cams.append(np.full(n, i, np.int64))
        dirs.append(d)
        rgbs.append(c)
        mir.append(np.full(n, v.kind == "mirror"))
        unc.append(np.full(n, v.uncertain))
    t = lambda a, dt=None: torch.from_numpy(np.concatenate(a)).to(device=device, dtype=dt)  # noqa: E731
    bank = RayBank(t(cams), t(dirs, torch.float32), t(rgbs, torch.float32), t(mir), t(unc))
    init = torch.from_numpy(np.stack([v.camera.c2w for v in views])).to(device=device, dtype=torch.float32)
    mask = torch.tensor([v.refine for v in views], device=device)
    return TrainingSet(spec, views, bank, init, mask, mirror_ids)
