"""Volume rendering (paper Eqn. 1), with the rendered variance beta_hat^2 of Sec. IV-C.

A NeRF renders a pixel by marching its ray r(t) = o + t d through a density field sigma and a
colour field c, and alpha-compositing N_s samples t_1 < ... < t_N (the quadrature of Eqn. 1):

    alpha_j = 1 - exp(-sigma_j delta_j)                 (opacity of the segment around t_j)
    T_j     = exp(-sum_{k<j} sigma_k delta_k)           (transmittance, T(t) of Eqn. 1)
    w_j     = T_j alpha_j                               (the weight of sample j)
    C_hat   = sum_j w_j c_j + (1 - sum_j w_j) * c_bg    (the background c_bg, below)

The background (`background`): white (flipviz: the datasets' background, so space no view saw
stays white), learned (one RGB colour, trained), or last (the official code: its last interval is
1e10 long, so the field's colour at the ray's far end c(x_N) is the background, and space no view
saw shows whatever the field holds there: fog). Rays that miss the scene box are never sampled and
show white (learned: the learned colour).

Uncertainty (Sec. IV-C) gives each sample a variance beta_bar_j^2 = beta_min^2 + softplus(raw_j)
and composites it along the ray. Two choices (`beta2_mode`):

    "linear":   beta_hat^2 = sum_j w_j   beta_bar_j^2 + (1 - sum_j w_j)   beta_min^2
    "variance": beta_hat^2 = sum_j w_j^2 beta_bar_j^2 + (1 - sum_j w_j^2) beta_min^2

"linear" is what the official code does (the colour's compositing applied to the variance);
"variance" is the variance of the weighted sum sum_j w_j c_j of independent Gaussians. In both,
the weight the ray does not spend on samples goes to the background (and, for "variance", to the
lost sum_j w_j (1 - w_j)), which has variance beta_min^2. Both therefore equal
beta_min^2 + sum_j w_j^p softplus(raw_j) with p = 1 or 2, so beta_hat^2 >= beta_min^2 on every
ray, including rays that miss the scene (beta_hat^2 = beta_min^2 exactly).

The official code composites linearly, sum_j w_j beta_bar_j^2; that is flipviz's default.

Samples are placed inside the scene box only (rays that miss the box are never sampled), evenly
over [max(near, t_in), min(far, t_out)], with stratified jitter while training. The field decides
where it evaluates (`Field.query`): the grid computes density only inside its occupancy mask and
colour only where the weight w_j is large enough; the NeRF MLP computes everything everywhere.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import Tensor


class Field(Protocol):
    """What the renderer needs from a radiance field (grid_field.py, nerf_field.py)."""

    with_beta: bool  # the field has the variance head of Sec. IV-C

    def query(
        self, x: Tensor, d: Tensor
    ) -> tuple[Tensor, Callable[[Tensor, Tensor | None], tuple[Tensor, Tensor, Tensor | None]]]:
        """Samples x (R, N, 3) on rays with directions d (R, 3) -> sigma (R, N), and colour(w, rows): weights
        w (B, N) of the rays `rows` (B,) (None: all R) -> flat indices into w (K,) of the samples it
        coloured, rgb (K, 3), beta raw (K,)."""
        ...


def ray_box(origins: Tensor, dirs: Tensor, bbox: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test: entry and exit distances (R,) of rays with the axis-aligned box bbox (2,3)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (bbox[0] - origins) * inv
    t1 = (bbox[1] - origins) * inv
    t_in = torch.minimum(t0, t1).amax(-1)
    t_out = torch.maximum(t0, t1).amin(-1)
    return t_in, t_out


MIN_DEPTH = 0.05  # closest sample to a camera at inference (world units)


def render_rays(
    field: Field,
    origins: Tensor,
    dirs: Tensor,
    *,
    bbox: Tensor,
    near: float,
    far: float,
    n_samples: int,
    training: bool,
    beta_min: float,
    beta2_mode: str = "linear",
    background: str = "white",
    background_rgb: Tensor | None = None,
) -> dict[str, Tensor]:
    """Render R rays (origins (R,3), unit dirs (R,3)); see the module docstring for the maths.

    Returns rgb (R,3), depth (R,) (expected termination distance, background at `far`),
    opacity (R,) = sum_j w_j, sigma_mean (R,) = (1/N_s) sum_j sigma(t_j), and, when with_beta,
    beta2 (R,) = beta_hat^2.
    """
    with_beta = field.with_beta
    if beta2_mode not in ("linear", "variance"):
        raise ValueError(f"beta2_mode must be 'linear' or 'variance', got {beta2_mode!r}")
    if background not in ("white", "learned", "last") or (background == "learned") != (background_rgb is not None):
        raise ValueError(f"background must be white, last, or learned with its colour; got {background!r}")
    R, N, dev = origins.shape[0], n_samples, origins.device
    dtype = origins.dtype
    rgb = torch.ones(R, 3, device=dev, dtype=dtype) if background_rgb is None else background_rgb.expand(R, 3)
    depth = torch.full((R,), float(far), device=dev, dtype=dtype)
    opacity = torch.zeros(R, device=dev, dtype=dtype)
    sigma_mean = torch.zeros(R, device=dev, dtype=dtype)
    beta2 = torch.full((R,), beta_min**2, device=dev, dtype=dtype)

    # Rays that miss the box stay background. Training samples [near, far] (the cameras' orbit);
    # any other render (novel or browser cameras, near or far) samples the whole box segment.
    with torch.no_grad():
        t_in, t_out = ray_box(origins, dirs, bbox)
        if training:
            t_in, t_out = t_in.clamp_min(near), t_out.clamp_max(far)
        else:
            t_in = t_in.clamp_min(MIN_DEPTH)
        hit = torch.nonzero(t_out > t_in + 1e-6).squeeze(-1)
    out = {"rgb": rgb, "depth": depth, "opacity": opacity, "sigma_mean": sigma_mean}
    if with_beta:
        out["beta2"] = beta2
    if hit.numel() == 0:
        if training:  # keep the graph connected so backward() works on an all-miss batch
            zero = 0.0 * origins.sum() + 0.0 * dirs.sum()
            out = {k: v + zero for k, v in out.items()}
        return out

    o, d = origins.index_select(0, hit), dirs.index_select(0, hit)  # (index_select: its backward adds rows)
    t0, t1 = t_in[hit], t_out[hit]
    Rh = o.shape[0]
    with torch.no_grad():
        u = (torch.arange(N, device=dev, dtype=dtype) + 0.5) / N  # bin centres
        if training:  # stratified sampling: one uniform jitter per bin
            u = u + (torch.rand(Rh, N, device=dev, dtype=dtype) - 0.5) / N
        else:
            u = u.expand(Rh, N)
        span = (t1 - t0)[:, None]
        t = t0[:, None] + span * u  # (Rh, N)
        delta = (span / N).expand(Rh, N)  # segment lengths (equal bins)
    x = o[:, None, :] + t[..., None] * d[:, None, :]  # (Rh, N, 3), differentiable in o, d
    sigma, colour = field.query(x, d)  # sigma (Rh, N)
    if background == "last":  # c_bg = c(x_N), the field's colour at the far end (its own beta is not used)
        c_bg = field.color(x[:, -1], d)[0]  # (Rh, 3)
        rgb = rgb.index_put((hit,), c_bg)  # each ray's background; the composited ones are replaced below
    else:
        c_bg = 1.0 if background_rgb is None else background_rgb  # white, or the learned colour (3,)

    # A ray with no density on any sample (all in the grid's empty space, outside its occupancy mask)
    # shows its background as it is. Only the B others are composited: the same values, fewer samples.
    with torch.no_grad():
        busy = torch.nonzero(sigma.amax(-1) > 0).squeeze(-1)
    rows = None if busy.numel() == Rh else busy  # (B,) of the Rh rays; None: all
    if rows is not None:
        sigma, t, delta, hit = (v.index_select(0, rows) for v in (sigma, t, delta, hit))
        c_bg = c_bg.index_select(0, rows) if background == "last" else c_bg
    B = sigma.shape[0]

    # Eqn. 1, discretised: alpha_j, T_j = exp(-sum_{k<j} sigma_k delta_k), w_j = T_j alpha_j.
    tau = sigma * delta
    alpha = 1.0 - torch.exp(-tau)
    T = torch.exp(-torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau, -1)[:, :-1]], -1))
    w = T * alpha  # (B, N)

    keep, c, raw = colour(w, rows)  # the samples the field coloured: flat indices into w (K,), rgb (K, 3), raw (K,)
    rid, wk = keep // N, w.reshape(-1).index_select(0, keep)  # their ray and weight
    acc = w.sum(-1)  # opacity sum_j w_j
    col = torch.zeros(B, 3, device=dev, dtype=dtype).index_add(0, rid, wk[:, None] * c)  # sum_j w_j c_j
    dep = (w * t).sum(-1)
    h_rgb = col + (1.0 - acc)[:, None] * c_bg
    h_depth = dep + (1.0 - acc) * far
    out["rgb"] = rgb.index_put((hit,), h_rgb)
    out["depth"] = depth.index_put((hit,), h_depth)
    out["opacity"] = opacity.index_put((hit,), acc)
    out["sigma_mean"] = sigma_mean.index_put((hit,), sigma.mean(-1))  # (1/N_s) sum_j sigma(t_j)
    if with_beta:
        wp = wk if beta2_mode == "linear" else wk * wk
        # beta_bar^2 = beta_min^2 + softplus(raw) (Sec. IV-C); composited as in the docstring.
        extra = torch.zeros(B, device=dev, dtype=dtype).index_add(0, rid, wp * F.softplus(raw))
        out["beta2"] = beta2.index_put((hit,), beta_min**2 + extra)
    return out
