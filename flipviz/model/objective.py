"""The training objective (paper Sec. IV-C), in one function, with its warm-up.

Per training ray, with target colour C and rendered colour C_hat (renderer.py):

    certain rays:    L_p(r)  = ||C - C_hat||^2                                        (Eqn. 2)
    uncertain rays:  L_u(r') = ||C - C_hat||^2 / (2 beta_hat^2) + log(beta_hat^2) / 2
                               + (w / N_s) sum_j sigma(t_j)                             (Eqn. 7)

||.||^2 sums the three channels. beta_hat^2 is the rendered variance (renderer.py); the last term
keeps the density from growing where the variance explains the error away.

Warm-up: before `nll_start` every ray uses L_p (the paper starts the NLL at 10k of 50k iterations).

Mixing the two: the paper fixes a certain ray's variance at beta_min^2, so under the NLL its loss is
||C - C_hat||^2 / (2 beta_min^2) + const. The objective is the batch mean of these per-ray NLLs
times the constant 2 beta_min^2 / 3: a certain ray then contributes exactly its per-channel squared
error, in the warm-up and after it, so the switch changes nothing for certain rays.

Two choices where the official code differs from the paper's text (the authors' setting):
- `channels` "mean": ||C - C_hat||^2 / 3 in the NLL (the code's mean over channels), so the optimal
  beta^2 is the per-channel squared error, a third of the sum's: mirrored rays weigh 3x more. The
  constant then is 2 beta_min^2, and certain rays still contribute their per-channel squared error.
- `density_on` "all": the density term reaches every ray once the NLL is on, B/L's included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Objective:
    """L(batch) = mean over rays of L_p (warm-up) or of the mixed NLL above (from `nll_start` on)."""

    beta_min: float = 0.1
    density_weight: float = 0.01
    """w of the density regulariser (w / N_s) sum_j sigma(t_j) (Eqn. 7)."""
    nll_start: int = 0
    """First step on which uncertain rays use the NLL."""
    channels: str = "sum"
    """||C - C_hat||^2 of the NLL summed over RGB (the paper's norm) or averaged ("mean": the code's)."""
    density_on: str = "uncertain"
    """The density term on the uncertain rays (Eqn. 7) or on every ray ("all": the code's)."""

    def __call__(self, out: dict[str, Tensor], target: Tensor, uncertain: Tensor, step: int) -> Tensor:
        """out: the renderer's rgb (R, 3) (+ beta2, sigma_mean (R,) once the NLL is on); target (R, 3);
        uncertain (R,) bool: the rays whose variance is learned."""
        sq = (out["rgb"] - target).pow(2).sum(-1)  # ||C - C_hat||^2, (R,)
        everywhere = self.density_on == "all"
        if step < self.nll_start or not (bool(uncertain.any()) or everywhere):
            return sq.mean() / 3.0  # L_p as the MSE over rays and channels
        k = 3.0 if self.channels == "mean" else 1.0  # the NLL's error: the sum, or the mean over channels
        b2min, density = self.beta_min**2, self.density_weight * out["sigma_mean"]  # (w / N_s) sum_j sigma_j
        nll_c = sq / k / (2.0 * b2min) + (density if everywhere else 0.0)  # a certain ray: beta_hat^2 = beta_min^2
        if not bool(uncertain.any()):
            return (2.0 * b2min * k / 3.0) * nll_c.mean()
        nll_u = sq / k / (2.0 * out["beta2"]) + 0.5 * torch.log(out["beta2"]) + density  # Eqn. 7
        return (2.0 * b2min * k / 3.0) * torch.where(uncertain, nll_u, nll_c).mean()


def psnr(mse: float) -> float:
    """Peak signal-to-noise ratio (dB) of a mean squared error of [0, 1] images: -10 log10(mse)."""
    return -10.0 * math.log10(max(float(mse), 1e-12))
