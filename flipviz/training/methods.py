"""Which views, pose refinement and uncertainty each of the five methods uses (paper Table I).

| method | trains on              | pose refinement (BA) | learned beta^2 on   |
|--------|------------------------|----------------------|---------------------|
| bl     | 8 inputs               | none                 | -                   |
| bl+u   | 8 inputs               | none                 | all input rays      |
| flip   | 8 inputs + 8 mirrors   | mirrored poses       | -                   |
| flip+u | 8 inputs + 8 mirrors   | mirrored poses       | mirrored rays       |
| upper  | 8 inputs + 8 upper     | none                 | -                   |

`cfg.flip.ba = False` and `cfg.flip.uncertainty = False` switch BA / beta^2 off (paper Table II ablation);
`cfg.flip.refine = "all"` lets BA move the original input poses too. What the mirrors themselves are
is `flipviz.training.flip`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch

from flipviz.data.cameras import Camera, View
from flipviz.data.rays import RayBank
from flipviz.errors import UserError
from flipviz.training.config import METHODS, TrainConfig

ViewKind = Literal["input", "mirror", "upper"]


@dataclass(frozen=True)
class MethodSpec:
    name: str
    mirrors: bool  # add the 8 flipped images with their estimated poses
    upper: bool  # add the 8 Upper views (true images of the unobserved side)
    ba: bool  # refine the mirrored poses (BARF-style), plus the inputs' when refine_inputs
    refine_inputs: bool
    uncertain_inputs: bool  # learned beta^2 on input rays
    uncertain_mirrors: bool  # learned beta^2 on mirrored rays

    @property
    def uses_beta(self) -> bool:
        return self.uncertain_inputs or self.uncertain_mirrors

    def without_mirrors(self) -> MethodSpec:
        """No mirrored view (nor their BA and uncertainty): a Flip run whose estimated plane is not confident."""
        return replace(self, mirrors=False, ba=False, refine_inputs=False, uncertain_mirrors=False)


def method_spec(cfg: TrainConfig) -> MethodSpec:
    m = cfg.method
    if m not in METHODS:
        raise UserError(f"unknown method {m!r}; choose one of {', '.join(METHODS)}")
    flip = m in ("flip", "flip+u")
    ba = flip and cfg.flip.ba
    return MethodSpec(
        name=m,
        mirrors=flip,
        upper=m == "upper",
        ba=ba,
        refine_inputs=ba and cfg.flip.refine == "all",
        uncertain_inputs=m == "bl+u" and cfg.flip.uncertainty,
        uncertain_mirrors=m == "flip+u" and cfg.flip.uncertainty,
    )


@dataclass
class TrainView:
    kind: ViewKind
    camera: Camera  # initial pose
    image: np.ndarray  # (H, W, 3) float32 target (the flipped image for mirrors)
    refine: bool  # pose is refined by BA
    uncertain: bool  # its rays use the learned-variance loss
    source: str = ""  # mirrors: the input view it was flipped from
    keep: np.ndarray | None = None  # (H, W) bool: the pixels it trains on (None: all)


@dataclass
class TrainingSet:
    views: list[TrainView]
    bank: RayBank  # every pixel of every view
    init_c2w: torch.Tensor  # (V, 4, 4) float32 initial poses
    refine_mask: torch.Tensor  # (V,) bool: which poses BA refines
    uncertain: torch.Tensor  # (V,) bool: which views' rays learn beta^2
    mirror_ids: list[int] = field(default_factory=list)  # indices of the mirrored views, in order

    @property
    def mirror_views(self) -> list[TrainView]:
        return [self.views[i] for i in self.mirror_ids]


def build_training_set(
    spec: MethodSpec,
    inputs: list[View],
    mirrors: list[TrainView] | None = None,
    uppers: list[View] | None = None,
    device: str | torch.device = "cpu",
) -> TrainingSet:
    """The views of `spec`'s method: inputs, then its mirrors or Upper views, and their ray bank."""
    views = [TrainView("input", v.camera, v.rgb, spec.refine_inputs, spec.uncertain_inputs) for v in inputs]
    mirror_ids: list[int] = []
    if spec.mirrors:
        if not mirrors:
            raise ValueError(f"method {spec.name} needs the mirrored views")
        mirror_ids = list(range(len(views), len(views) + len(mirrors)))
        views += mirrors
    if spec.upper:
        if not uppers:
            raise ValueError("method upper needs the Upper views")
        views += [TrainView("upper", v.camera, v.rgb, False, False) for v in uppers]
    bank = RayBank.from_images([v.camera for v in views], [v.image for v in views], device, [v.keep for v in views])
    init = torch.from_numpy(np.stack([v.camera.c2w for v in views])).to(device=device, dtype=torch.float32)
    flags = lambda attr: torch.tensor([getattr(v, attr) for v in views], device=device)  # noqa: E731
    return TrainingSet(views, bank, init, flags("refine"), flags("uncertain"), mirror_ids)
