"""What both radiance fields share: their scene box, and points mapped into it."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn


class BoxField(nn.Module):
    """A field defined inside the axis-aligned box bbox (2, 3); `with_beta`: it has the variance head."""

    def __init__(self, bbox: np.ndarray, with_beta: bool, device: torch.device | str) -> None:
        super().__init__()
        self.with_beta = with_beta
        self.register_buffer("lo", torch.as_tensor(bbox[0], dtype=torch.float32, device=device))
        self.register_buffer("hi", torch.as_tensor(bbox[1], dtype=torch.float32, device=device))

    def normalise(self, x: Tensor) -> Tensor:
        """Points (P, 3) -> box coordinates in [-1, 1]^3 (grid_sample's convention)."""
        return (x - self.lo) / (self.hi - self.lo) * 2.0 - 1.0
