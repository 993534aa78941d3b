"""What both radiance fields share: their scene box, points mapped into it, and the variance head."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn


class BoxField(nn.Module):
    """A field defined inside the axis-aligned box bbox (2, 3); `with_beta`: it has the variance head
    of Sec. IV-C, on the colour branch (`beta_from` colour: position and view direction, flipviz) or
    on the position features alone (position: the official code's, from the density trunk)."""

    def __init__(
        self, bbox: np.ndarray, with_beta: bool, device: torch.device | str, beta_from: str = "colour"
    ) -> None:
        super().__init__()
        if beta_from not in ("colour", "position"):
            raise ValueError(f"beta_from must be 'colour' or 'position', got {beta_from!r}")
        self.with_beta, self.beta_from = with_beta, beta_from
        self.register_buffer("lo", torch.as_tensor(bbox[0], dtype=torch.float32, device=device))
        self.register_buffer("hi", torch.as_tensor(bbox[1], dtype=torch.float32, device=device))

    def normalise(self, x: Tensor) -> Tensor:
        """Points (P, 3) -> box coordinates in [-1, 1]^3 (grid_sample's convention)."""
        return (x - self.lo) / (self.hi - self.lo) * 2.0 - 1.0

    def beta_outputs(self) -> int:
        """Outputs the colour head adds for the variance: 1 (beta from colour) or 0."""
        return int(self.with_beta and self.beta_from == "colour")

    def init_beta(self, position_dim: int, colour_head: nn.Linear, beta_init: float) -> None:
        """The variance head starts at a small per-sample variance: softplus(raw) = beta_init^2."""
        if not self.with_beta:
            return
        start = math.log(math.expm1(beta_init**2))
        if self.beta_from == "position":
            self.beta_head = nn.Linear(position_dim, 1)
            with torch.no_grad():
                self.beta_head.bias.fill_(start)
        else:
            with torch.no_grad():
                colour_head.bias[3] = start

    def beta_raw(self, position_features: Tensor, colour_out: Tensor) -> Tensor | None:
        """beta raw (P,) from the position features (P, F) or the colour head's 4th output (P, 4)."""
        if not self.with_beta:
            return None
        return self.beta_head(position_features)[:, 0] if self.beta_from == "position" else colour_out[:, 3]
