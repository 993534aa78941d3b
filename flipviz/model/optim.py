"""The optimiser settings both fields share: Adam and an exponential learning-rate decay; and the grid's
lookups, whose gradient goes into a buffer kept across steps.

A step of the grid field looks up about 40k of its 0.6-2.1M voxels. autograd's gather (index_select) makes
each lookup's gradient a new dense grid: allocated, zero-filled, scattered into, then added to the other
lookups' (the TV regulariser's): 11 ms of a 41 ms chair step at 128^3 on 2 cores (docs/PERFORMANCE.md).
`gather_rows` scatters into the grid's `.grad` in place instead, which the trainer zeroes in place each
step (`zero_grad(set_to_none=False)`). Adam then reads the same gradient as before: the update is unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


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


class _GatherRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, grid: Tensor, idx: Tensor) -> Tensor:
        ctx.grid = grid
        ctx.save_for_backward(idx)
        return grid.view(-1, grid.shape[-1]).index_select(0, idx)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (idx,) = ctx.saved_tensors
        grid = ctx.grid
        if grid.grad is None:  # made once; zero_grad(set_to_none=False) keeps it
            grid.grad = torch.zeros_like(grid)
        grid.grad.view(-1, grid.shape[-1]).index_add_(0, idx, grad)
        return None, None  # the gradient is in grid.grad already


def gather_rows(grid: Tensor, idx: Tensor) -> Tensor:
    """grid.view(-1, C)[idx] (n, C) for a channels-last grid (Z, Y, X, C). For a parameter, the backward adds
    into grid.grad in place (the module docstring): `torch.autograd.grad` does not see that gradient, so a
    grid that is not a parameter (a test's, differentiated with it) takes autograd's own gather."""
    if not (torch.is_grad_enabled() and isinstance(grid, nn.Parameter) and grid.requires_grad):
        return grid.view(-1, grid.shape[-1]).index_select(0, idx)
    return _GatherRows.apply(grid, idx)
