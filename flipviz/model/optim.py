"""The optimiser settings both fields share: Adam and an exponential learning-rate decay."""

from __future__ import annotations

import torch


def adam(groups: list[dict], eps: float, betas: tuple[float, float]) -> torch.optim.Optimizer:
    """Adam over `groups` (each keeps its base lr in "lr0"); torch's fused kernel where supported."""
    for g in groups:
        g.setdefault("lr0", g["lr"])
    try:
        return torch.optim.Adam(groups, eps=eps, betas=betas, fused=True)
    except (RuntimeError, TypeError):  # fused is not supported for this device / dtype
        return torch.optim.Adam(groups, eps=eps, betas=betas)


def decay_lr(optimizer: torch.optim.Optimizer, step: int, total_steps: int, final_ratio: float) -> float:
    """lr = lr0 * final_ratio^(step / total_steps) for every group; returns the factor."""
    f = final_ratio ** (min(step, total_steps) / max(total_steps, 1))
    for g in optimizer.param_groups:
        g["lr"] = g["lr0"] * f
    return f
