"""The vanilla NeRF MLP field (Mildenhall et al.), the paper's setting, behind the grid's interface.

    F_Theta(x, d) -> (sigma, c, beta raw):  8 x 256 ReLU layers on PE(x) (10 bands, skip at layer
    4), sigma from the trunk, then a 128-wide layer on [trunk feature, PE(d) (4 bands)] -> c (and
    the variance head of Sec. IV-C). All sizes are configurable (FieldConfig.nerf_*).

Differences from the original: one network and `n_samples` stratified samples inside the scene box
(no hierarchical coarse/fine pair); points are normalised to [-1, 1] by the box.

BARF's coarse-to-fine schedule: with `nerf_barf_c2f = (start, end)` the k-th positional-encoding
band of x is weighted by (1 - cos(pi * clamp(a - k, 0, 1))) / 2, a = L (p - start) / (end - start),
p = training progress in [0, 1], so that pose refinement first sees a smooth field.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn


class NerfField(nn.Module):
    two_stage = False

    def __init__(self, cfg, bbox: np.ndarray, with_beta: bool, device: torch.device | str = "cpu"):
        super().__init__()
        self.cfg = cfg
        self.with_beta = with_beta
        self.register_buffer("lo", torch.as_tensor(bbox[0], dtype=torch.float32, device=device))
        self.register_buffer("hi", torch.as_tensor(bbox[1], dtype=torch.float32, device=device))
        self.register_buffer("progress", torch.ones((), device=device))  # for BARF's c2f schedule
        W, L, Ld = cfg.nerf_width, cfg.nerf_pe, cfg.nerf_dir_pe
        in_x, in_d = 3 + 6 * L, 3 + 6 * Ld
        self.skip = cfg.nerf_depth // 2
        self.trunk = nn.ModuleList()
        dim = in_x
        for i in range(cfg.nerf_depth):
            if i == self.skip and i > 0:
                dim += in_x
            self.trunk.append(nn.Linear(dim, W))
            dim = W
        self.sigma_head = nn.Linear(W, 1)
        self.feature = nn.Linear(W, W)
        self.view = nn.Linear(W + in_d, W // 2)
        self.out = nn.Linear(W // 2, 4 if with_beta else 3)
        if with_beta:
            with torch.no_grad():
                self.out.bias[3] = math.log(math.expm1(cfg.beta_init**2))
        self.to(device)

    def _pe(self, x: Tensor, n: int, barf: bool) -> Tensor:
        if n == 0:
            return x
        freqs = 2.0 ** torch.arange(n, device=x.device, dtype=x.dtype)
        xb = x[..., None, :] * (math.pi * freqs[:, None])  # (P, n, 3)
        enc = torch.cat([torch.sin(xb), torch.cos(xb)], -1)  # (P, n, 6)
        c2f = self.cfg.nerf_barf_c2f
        if barf and c2f is not None:
            a = (float(self.progress) - c2f[0]) / (c2f[1] - c2f[0]) * n
            k = torch.arange(n, device=x.device, dtype=x.dtype)
            wk = (1.0 - torch.cos(math.pi * (a - k).clamp(0.0, 1.0))) / 2.0
            enc = enc * wk[:, None]
        return torch.cat([x, enc.flatten(-2)], -1)

    def forward(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        xn = (x - self.lo) / (self.hi - self.lo) * 2.0 - 1.0
        px = self._pe(xn, self.cfg.nerf_pe, barf=True)
        h = px
        for i, layer in enumerate(self.trunk):
            if i == self.skip and i > 0:
                h = torch.cat([h, px], -1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.sigma_head(h)[:, 0])
        h = torch.cat([self.feature(h), self._pe(d, self.cfg.nerf_dir_pe, barf=False)], -1)
        out = self.out(F.relu(self.view(h)))
        return sigma, torch.sigmoid(out[:, :3]), (out[:, 3] if self.with_beta else None)

    def occupied(self, x: Tensor) -> Tensor:
        return torch.ones(x.shape[0], dtype=torch.bool, device=x.device)

    def density(self, x: Tensor) -> Tensor:
        return self.forward(x, torch.zeros_like(x))[0]

    def color(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor | None]:
        _, rgb, raw = self.forward(x, d)
        return rgb, raw

    def regulariser(self) -> Tensor:
        return self.sigma_head.weight.new_zeros(())

    def param_groups(self) -> list[dict]:
        return [{"params": list(self.parameters()), "lr": self.cfg.nerf_lr, "name": "mlp"}]
