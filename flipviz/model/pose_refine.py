"""BARF-style bundle adjustment of chosen cameras (paper Sec. IV-B, BA-NeRF).

What BARF adds to a NeRF: the camera poses become parameters too. Each camera i gets a twist
xi_i in se(3) (pypose ordering: [tx, ty, tz, rx, ry, rz], i.e. translation first; Exp gives an
SE(3) element stored as [t, q_xyzw]), initialised at zero, and its pose is

    c2w_i = c2w_i^init @ Exp(xi_i)          (the correction acts on the camera side)

so xi_i is a small motion expressed in camera i's own frame. BARF composes on the world side
instead (its world-to-camera pose is applied after the correction, i.e. c2w = Exp(xi)^-1 @ c2w_init).
flipviz uses the camera side because a mirrored camera sits 4 units from the world origin: a
world-side rotation swings the camera around the origin, coupling rotation and translation, while
a camera-side one turns it in place, so the 6 components of xi_i are independent. Rays are generated
from the refined c2w with `flipviz.data.cameras.rays_from_c2w`, so the photometric loss is
differentiable in xi_i. Only cameras with refine[i] = True move (in the paper: the mirrored
cameras); the others keep exactly their initial pose.

Coarse-to-fine: BARF anneals the positional-encoding bands of its MLP over [0.1, 0.5] of training
so that early pose gradients come from a smooth field. The NeRF field does the same
(FieldConfig.nerf_barf_c2f); the grid field gets it from its coarse-to-fine schedule (a 64^3 grid
is a low-pass version of the 128^3 one, and the grids start blurred), so nothing extra is done.

Optimiser: its own Adam, lr 1e-3 decaying exponentially to 1e-5 over training (as BARF).
"""

from __future__ import annotations

import numpy as np
import pypose as pp
import torch
from torch import Tensor, nn

from flipviz.model.optim import decay_lr


class PoseRefiner(nn.Module):
    def __init__(
        self,
        init_c2w: np.ndarray | Tensor,
        refine: np.ndarray | Tensor,
        total_steps: int,
        lr: float = 1e-3,
        lr_end: float = 1e-5,
        device: torch.device | str = "cpu",
    ):
        super().__init__()
        c2w = torch.as_tensor(np.asarray(init_c2w), dtype=torch.float32, device=device)
        mask = torch.as_tensor(np.asarray(refine), dtype=torch.bool, device=device)
        if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
            raise ValueError(f"init_c2w must be (M,4,4), got {tuple(c2w.shape)}")
        if mask.shape != c2w.shape[:1]:
            raise ValueError(f"refine mask must be ({c2w.shape[0]},), got {tuple(mask.shape)}")
        self.register_buffer("init_c2w", c2w)
        self.register_buffer("refine", mask)
        self.xi = nn.Parameter(torch.zeros(c2w.shape[0], 6, device=device))  # se(3): [t, r]
        self.total_steps, self.lr, self.lr_end = int(total_steps), float(lr), float(lr_end)

    def delta(self) -> Tensor:
        """Exp(xi) as (M,4,4) matrices; identity for cameras that are not refined."""
        xi = self.xi * self.refine[:, None].to(self.xi.dtype)
        return pp.se3(xi).Exp().matrix()

    def forward(self) -> Tensor:
        """Current camera-to-world poses (M,4,4): c2w_init @ Exp(xi)."""
        return self.init_c2w @ self.delta()

    def make_optimizer(self) -> torch.optim.Optimizer:
        return torch.optim.Adam([{"params": [self.xi], "lr": self.lr, "lr0": self.lr}])

    def adjust_lr(self, optimizer: torch.optim.Optimizer, step: int) -> None:
        """lr * (lr_end / lr)^(step / total_steps)."""
        decay_lr(optimizer, step, self.total_steps, self.lr_end / self.lr)
