"""Losses: the photometric loss of vanilla NeRF and the uncertainty NLL of Sec. IV-C."""

from __future__ import annotations

import torch
from torch import Tensor


def photometric_mse(rgb: Tensor, target: Tensor) -> Tensor:
    """L_p (paper Eqn. nerf_loss), as a mean over rays and channels (so PSNR = -10 log10 L_p)."""
    return (rgb - target).pow(2).mean()


def uncertainty_nll(rgb: Tensor, target: Tensor, beta2: Tensor, sigma_mean: Tensor, w: float) -> Tensor:
    """Sec. IV-C: L(r') = ||C - C_hat||^2 / (2 beta_hat^2) + log(beta_hat^2) / 2 + (w / N_s) sum_j sigma(t_j).

    rgb, target (R,3); beta2 (R,) = beta_hat^2; sigma_mean (R,) = (1/N_s) sum_j sigma(t_j).
    ||.||^2 sums the three channels (as in the paper); the mean is over rays.
    """
    if beta2.shape != rgb.shape[:1] or sigma_mean.shape != rgb.shape[:1]:
        raise ValueError(f"beta2 {tuple(beta2.shape)} and sigma_mean {tuple(sigma_mean.shape)} must be (R,) for rgb {tuple(rgb.shape)}")
    sq = (rgb - target).pow(2).sum(-1)
    return (sq / (2.0 * beta2) + 0.5 * torch.log(beta2) + w * sigma_mean).mean()


def psnr(mse: Tensor | float) -> float:
    """Peak signal-to-noise ratio (dB) of a mean squared error of [0, 1] images."""
    m = float(mse)
    return float("inf") if m <= 0 else -10.0 * float(torch.log10(torch.tensor(m)))
