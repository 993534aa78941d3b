"""The vanilla NeRF MLP field (Mildenhall et al.), the paper's setting, behind the grid's interface.

    F_Theta(x, d) -> (sigma, c, beta raw):  8 x 256 ReLU layers on PE(x) (10 bands, skip at layer
    4), sigma from the trunk, then a 128-wide layer on [trunk feature, PE(d) (4 bands)] -> c (and
    the variance head of Sec. IV-C). All sizes are configurable (`NerfConfig`).

Differences from the original: one network and `n_samples` stratified samples inside the scene box
(no hierarchical coarse/fine pair); points are normalised to [-1, 1] by the box.

BARF's coarse-to-fine schedule: with `barf_c2f = (start, end)` the k-th positional-encoding
band of x is weighted by (1 - cos(pi * clamp(a - k, 0, 1))) / 2, a = L (p - start) / (end - start),
p = training progress in [0, 1], so that pose refinement first sees a smooth field.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flipviz.model.encoding import posenc
from flipviz.model.field_base import BoxField
from flipviz.model.optim import adam


@dataclass
class NerfConfig:
    """The vanilla NeRF MLP and its optimiser."""

    depth: int = 8
    width: int = 256
    pe: int = 10
    """Positional-encoding bands of x."""
    dir_pe: int = 4
    """Positional-encoding bands of the view direction."""
    lr: float = 5e-4
    lr_decay: float = 0.1
    """The learning rate decays exponentially to lr * lr_decay at the end of training."""
    barf_c2f: tuple[float, float] | None = None
    """BARF's positional-encoding annealing window, e.g. (0.1, 0.5); None = off."""

    def build(
        self, bbox: np.ndarray, with_beta: bool, beta_init: float, device: torch.device | str, beta_from: str = "colour"
    ) -> NerfField:
        return NerfField(self, bbox, with_beta, beta_init, device, beta_from)


class NerfField(BoxField):
    def __init__(
        self,
        cfg: NerfConfig,
        bbox: np.ndarray,
        with_beta: bool,
        beta_init: float,
        device: torch.device | str = "cpu",
        beta_from: str = "colour",
    ):
        super().__init__(bbox, with_beta, device, beta_from)
        self.cfg = cfg
        self.register_buffer("progress", torch.ones((), device=device))  # for BARF's c2f schedule
        W, L, Ld = cfg.width, cfg.pe, cfg.dir_pe
        in_x, in_d = 3 + 6 * L, 3 + 6 * Ld
        self.skip = cfg.depth // 2
        self.trunk = nn.ModuleList()
        dim = in_x
        for i in range(cfg.depth):
            if i == self.skip and i > 0:
                dim += in_x
            self.trunk.append(nn.Linear(dim, W))
            dim = W
        self.sigma_head = nn.Linear(W, 1)
        self.feature = nn.Linear(W, W)
        self.view = nn.Linear(W + in_d, W // 2)
        self.out = nn.Linear(W // 2, 3 + self.beta_outputs())
        self.init_beta(W, self.out, beta_init)  # position features: the density trunk's
        self.to(device)

    def barf_weights(self) -> Tensor | None:
        """BARF's weight of each positional-encoding band of x at the current progress (None: off)."""
        c2f = self.cfg.barf_c2f
        if c2f is None:
            return None
        n = self.cfg.pe
        a = (float(self.progress) - c2f[0]) / (c2f[1] - c2f[0]) * n
        k = torch.arange(n, device=self.progress.device, dtype=torch.float32)
        return (1.0 - torch.cos(math.pi * (a - k).clamp(0.0, 1.0))) / 2.0

    def forward(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """x, d (P, 3) -> sigma (P,), rgb (P, 3), beta raw (P,) or None."""
        px = posenc(self.normalise(x), self.cfg.pe, math.pi, self.barf_weights())
        h = px
        for i, layer in enumerate(self.trunk):
            if i == self.skip and i > 0:
                h = torch.cat([h, px], -1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.sigma_head(h)[:, 0])
        v = torch.cat([self.feature(h), posenc(d, self.cfg.dir_pe, math.pi)], -1)
        out = self.out(F.relu(self.view(v)))
        return sigma, torch.sigmoid(out[:, :3]), self.beta_raw(h, out)

    def density(self, x: Tensor) -> Tensor:
        return self(x, torch.zeros_like(x))[0]

    def color(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor | None]:
        _, rgb, raw = self(x, d)
        return rgb, raw

    def lattice_shape(self) -> tuple[int, int, int]:
        """(Z, Y, X) of the lattice a point cloud of this field is sampled on (an MLP has no voxels)."""
        return (48, 48, 48)

    def query(
        self, x: Tensor, d: Tensor
    ) -> tuple[Tensor, Callable[[Tensor, Tensor | None], tuple[Tensor, Tensor, Tensor | None]]]:
        """Densities of samples x (R, N, 3) on rays d (R, 3); colour is computed with them, for all samples
        (of the rays `rows` the renderer composites: all but those whose density is 0 everywhere)."""
        R, N = x.shape[:2]
        sigma, rgb, raw = self(x.reshape(-1, 3), d[:, None, :].expand(R, N, 3).reshape(-1, 3))

        def colour(w: Tensor, rows: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
            if rows is None:
                return torch.arange(w.numel(), device=x.device), rgb, raw
            at = (rows[:, None] * N + torch.arange(N, device=x.device)).reshape(-1)  # w's samples among the R N
            return torch.arange(w.numel(), device=x.device), rgb[at], None if raw is None else raw[at]

        return sigma.view(R, N), colour

    def update_schedule(self, step: int, total_steps: int, step_len: float) -> bool:
        """BARF's progress p = step / total_steps; the parameters never change."""
        self.progress.fill_(step / max(total_steps, 1))
        return False

    def regulariser(self) -> Tensor:
        return self.sigma_head.weight.new_zeros(())

    def make_optimizer(self) -> torch.optim.Optimizer:
        return adam(
            [{"params": list(self.parameters()), "lr": self.cfg.lr, "name": "mlp"}], eps=1e-8, betas=(0.9, 0.999)
        )
