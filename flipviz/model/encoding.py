"""NeRF's positional encoding, the one used by both fields."""

from __future__ import annotations

import torch
from torch import Tensor


def posenc(x: Tensor, n_freqs: int, scale: float = 1.0, band_weights: Tensor | None = None) -> Tensor:
    """gamma(x) = [x, sin(scale 2^k x), cos(scale 2^k x)]_{k < n_freqs}: (P, D) -> (P, D (1 + 2 n_freqs)).

    The features of band k sit together ([sin, cos] of all D inputs), so that `band_weights` (n_freqs,)
    can scale whole bands (BARF's coarse-to-fine schedule). NeRF encodes positions in [-1, 1] with
    scale = pi; the grid's colour MLP encodes unit view directions with scale = 1.
    """
    if n_freqs == 0:
        return x
    freqs = scale * 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
    xb = x[..., None, :] * freqs[:, None]  # (P, n, D)
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], -1)  # (P, n, 2D)
    if band_weights is not None:
        enc = enc * band_weights[:, None]
    return torch.cat([x, enc.flatten(-2)], -1)
