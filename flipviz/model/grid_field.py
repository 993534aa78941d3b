"""A dense voxel-grid radiance field (DVGO / Plenoxels style), fast enough to train on a CPU.

What a NeRF is: a function F(x, d) -> (sigma, c) from a 3-D point x and a viewing direction d to
a density sigma and a colour c, turned into pixels by volume rendering (renderer.py, Eqn. 1).
Vanilla NeRF represents F with a large MLP (nerf_field.py); here F is mostly a lookup table:

    sigma(x) = softplus(V_density(x) + shift) / s     trilinear lookup in a (Z,Y,X,1) grid
    f(x)     = V_feat(x)                              C-channel feature grid (Z,Y,X,C), same resolution
    c, raw   = MLP(f(x), PE(d))                       tiny colour MLP (+ the beta head, Sec. IV-C)

`shift` makes every voxel almost transparent at start (alpha_init); s is the voxel size of the
first (coarsest) grid, so a raw value means the same opacity per voxel at every resolution.

What makes it fast on a CPU (measured on the 2-core development machine):
- the grids are channels-last (a voxel's C features are adjacent in memory), and a sample's eight
  trilinear corners and weights are computed once for both lookups: a gather of whole rows. The
  feature lookup of 14k samples in a 128^3 grid, forward and backward, takes 24 ms against
  grid_sample's 45 ms on per-channel planes (which this replaced: 600 lego steps 86 s -> 69 s);
- an occupancy mask (refreshed from the density every few steps, dilated, with a threshold
  relative to the current maximum) drops samples in empty space before any lookup;
- the renderer computes colour only where the sample weight exceeds 1e-4;
- coarse-to-fine: the grids start at `grid_res[0]` voxels along the longest box side and are
  trilinearly upsampled to the next resolution at fractions `upsample_at` of training. Early in
  training the field is therefore smooth (a blurred scene), which is also what BARF's
  coarse-to-fine positional-encoding schedule provides for pose refinement (pose_refine.py);
- a total-variation regulariser on the density (and features) against few-view floaters.
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
from flipviz.model.optim import adam, gather_rows


@dataclass
class GridConfig:
    """The dense voxel grid: its resolution schedule, occupancy mask, colour MLP and optimiser."""

    grid_res: tuple[int, ...] = (64, 128)
    """Voxels along the longest box side, coarse to fine."""
    upsample_at: tuple[float, ...] = (0.25,)
    """Training fractions at which the grid moves to the next resolution (one per step of grid_res)."""
    feat_dim: int = 6
    alpha_init: float = 1e-2
    """Initial opacity of one voxel (density starts very low)."""
    view_dependent: bool = True
    view_pe: int = 2
    mlp_width: int = 64
    mlp_layers: int = 2
    lr_density: float = 0.1
    lr_feat: float = 0.1
    lr_mlp: float = 1e-3
    lr_decay: float = 0.1
    """Learning rates decay exponentially to lr * lr_decay at the end of training."""
    tv_density: float = 1e-4
    tv_feat: float = 1e-5
    tv_samples: int = 8192
    """Random voxels per step on which the TV regulariser is estimated."""
    color_thresh: float = 1e-4
    """Colour is evaluated only where the sample weight exceeds this (from occ_start on; before,
    while every weight is still tiny, where it exceeds alpha_init / 100)."""
    occ_start: int = 50
    """Step from which the occupancy mask is refreshed (all True before, when every sample is looked up).
    50 (was 100): 1.06-1.13x faster training on lego at the same held-out PSNR (within 0.02 dB on 20
    views of its orbit's second turn, docs/results/speed_levers) and 25.75 dB on the default chair run,
    as before (docs/PERFORMANCE.md)."""
    occ_every: int = 50
    occ_thresh: float = 0.02
    """Voxel alpha (over one sample spacing) below min(occ_thresh, occ_rel * max alpha) is empty.
    Pruning this low-density haze also removes the white fog few-view training grows."""
    occ_rel: float = 0.05
    occ_dilate: int = 1

    def __post_init__(self) -> None:
        if len(self.upsample_at) != len(self.grid_res) - 1:
            raise ValueError("GridConfig.upsample_at needs one fraction per grid_res step")

    def build(
        self, bbox: np.ndarray, with_beta: bool, beta_init: float, device: torch.device | str, beta_from: str = "colour"
    ) -> GridField:
        return GridField(self, bbox, with_beta, beta_init, device, beta_from)


def axis_resolution(bbox: np.ndarray, res: int) -> tuple[int, int, int]:
    """Voxels per axis (x, y, z): `res` along the longest side, proportionally fewer elsewhere."""
    ext = np.asarray(bbox[1], dtype=np.float64) - np.asarray(bbox[0], dtype=np.float64)
    return tuple(max(8, int(round(res * e / ext.max()))) for e in ext)


def dilate(mask: Tensor, r: int) -> Tensor:
    """A (Z, Y, X) bool mask grown by r voxels in each axis (a (2r+1)^3 cube: max pooling, one axis at a time)."""
    for axis in range(3):
        grown = mask.clone()
        for k in range(1, r + 1):
            lo, hi = mask.narrow(axis, 0, mask.shape[axis] - k), mask.narrow(axis, k, mask.shape[axis] - k)
            grown.narrow(axis, k, mask.shape[axis] - k).logical_or_(lo)
            grown.narrow(axis, 0, mask.shape[axis] - k).logical_or_(hi)
        mask = grown
    return mask


class GridField(BoxField):
    def __init__(
        self,
        cfg: GridConfig,
        bbox: np.ndarray,
        with_beta: bool,
        beta_init: float,
        device: torch.device | str = "cpu",
        beta_from: str = "colour",
    ):
        super().__init__(bbox, with_beta, device, beta_from)
        self.cfg = cfg
        ext = np.asarray(bbox[1], dtype=np.float64) - np.asarray(bbox[0], dtype=np.float64)
        self.voxel0 = float(ext.max() / (cfg.grid_res[0] - 1))  # the scale s of the module docstring
        # shift: softplus(shift) * (voxel0 / s) = -log(1 - alpha_init)  (alpha of one voxel)
        self.shift = math.log(math.expm1(-math.log(1.0 - cfg.alpha_init)))
        rx, ry, rz = axis_resolution(bbox, cfg.grid_res[0])
        self.density_grid = nn.Parameter(torch.zeros(rz, ry, rx, 1, device=device))  # (Z, Y, X, 1)
        self.feat_grid = nn.Parameter(torch.zeros(rz, ry, rx, cfg.feat_dim, device=device))  # (Z, Y, X, C)
        nn.init.uniform_(self.feat_grid, -1e-4, 1e-4)
        # Occupancy mask (True = evaluate), at the density's resolution; all True until refreshed.
        self.register_buffer("occ", torch.ones(rz, ry, rx, dtype=torch.bool, device=device))
        self._occ_idx: Tensor | None = None  # flat indices of occupied voxels (for the TV)
        self.register_buffer("stage", torch.zeros((), dtype=torch.long, device=device))
        self.color_thresh = self._early_color_thresh()
        in_dim = cfg.feat_dim + (3 + 6 * cfg.view_pe if cfg.view_dependent else 0)
        layers: list[nn.Module] = []
        for _ in range(cfg.mlp_layers):
            layers += [nn.Linear(in_dim, cfg.mlp_width), nn.ReLU(inplace=True)]
            in_dim = cfg.mlp_width
        layers.append(nn.Linear(in_dim, 3 + self.beta_outputs()))
        self.rgbnet = nn.Sequential(*layers)
        self.init_beta(cfg.feat_dim, self.rgbnet[-1], beta_init)  # position features: the feature grid's
        self.to(device)

    def _early_color_thresh(self) -> float:
        return min(self.cfg.color_thresh, self.cfg.alpha_init / 100.0)

    # --- what the renderer calls -----------------------------------------------------------
    def query(
        self, x: Tensor, d: Tensor
    ) -> tuple[Tensor, Callable[[Tensor, Tensor | None], tuple[Tensor, Tensor, Tensor | None]]]:
        """Densities of samples x (R, N, 3) on rays d (R, 3), and their colouring by weight.

        sigma (R, N) is evaluated only where the occupancy mask is set (0 elsewhere). The returned
        `colour(w, rows)` takes the sample weights w (B, N) of the rays `rows` (B,) (None: all R) and
        evaluates colour (and beta) only where w > color_thresh: it returns the flat indices into w (K,),
        rgb (K, 3) and beta raw (K,).
        """
        R, N = x.shape[:2]
        x_flat = x.reshape(-1, 3)
        with torch.no_grad():
            occ = torch.nonzero(self.occupied(x_flat)).squeeze(-1)  # (P,) occupied samples
        corners = self.corners(x_flat.index_select(0, occ))  # (P, 8) voxel indices and weights, for both lookups
        sigma = torch.zeros(R * N, device=x.device, dtype=x.dtype).index_put((occ,), self._density(corners))

        def colour(w: Tensor, rows: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
            with torch.no_grad():  # w > 0 only where sigma > 0, so every kept sample is occupied
                keep = torch.nonzero(w.reshape(-1) > self.color_thresh).squeeze(-1)  # (K,) into w
                ray = keep // N if rows is None else rows[keep // N]  # (K,) their ray among the R
                at = torch.searchsorted(occ, ray * N + keep % N)  # (K,) rows of `corners` (both lists sorted)
            picked = (corners[0].index_select(0, at), corners[1].index_select(0, at))  # the kept samples' corners
            rgb, raw = self._color(picked, self.view_features(d).index_select(0, ray))
            return keep, rgb, raw

        return sigma.view(R, N), colour

    # --- lookups -------------------------------------------------------------------------
    def corners(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Points (P,3) -> flat indices (P,8) of their cell's corner voxels and trilinear weights (P,8).

        Voxel centres sit on the box's corners and faces (grid_sample's align_corners=True); points
        outside the box take the nearest face's values (padding_mode="border"). The weights are
        differentiable in x (pose refinement moves samples); the indices are not.
        """
        Z, Y, X = self.resolution
        size = torch.tensor([X - 1, Y - 1, Z - 1], device=x.device, dtype=x.dtype)
        u = ((x - self.lo) / (self.hi - self.lo) * size).clamp_min(0).minimum(size)  # (P,3) in voxels
        i0 = torch.minimum(u.detach().floor(), size - 1).clamp_min(0)  # lower corner, a whole cell inside
        f = u - i0  # (P,3) position within the cell, in [0, 1]
        i0 = i0.long()
        base = (i0[:, 2] * Y + i0[:, 1]) * X + i0[:, 0]  # (P,)
        bits = torch.tensor([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], device=x.device)  # z y x
        offset = bits @ torch.tensor([Y * X, X, 1], device=x.device)  # (8,)
        fz, fy, fx = f[:, 2:3], f[:, 1:2], f[:, 0:1]
        w = (  # w_k = prod over axes of (f or 1 - f), in the order of `bits`
            torch.cat([1 - fz, fz], 1)[:, :, None, None]
            * torch.cat([1 - fy, fy], 1)[:, None, :, None]
            * torch.cat([1 - fx, fx], 1)[:, None, None, :]
        ).reshape(-1, 8)
        return base[:, None] + offset, w

    @staticmethod
    def _lerp(grid: Tensor, corners: tuple[Tensor, Tensor]) -> Tensor:
        """Trilinear lookup in a channels-last grid (Z,Y,X,C) at `corners` -> (P, C)."""
        idx, w = corners
        rows = gather_rows(grid, idx.reshape(-1)).view(idx.shape[0], 8, grid.shape[-1])  # (P, 8, C)
        return torch.bmm(w[:, None, :], rows)[:, 0]  # sum_k w_k V[corner_k]

    def occupied(self, x: Tensor) -> Tensor:
        Z, Y, X = self.occ.shape
        size = torch.tensor([X - 1, Y - 1, Z - 1], device=x.device, dtype=x.dtype)
        i = ((x - self.lo) / (self.hi - self.lo) * size).round().long()
        i = torch.minimum(i.clamp_min(0), size.long())
        return self.occ.view(-1)[(i[:, 2] * Y + i[:, 1]) * X + i[:, 0]]

    def density(self, x: Tensor) -> Tensor:
        """sigma (P,) at points x (P, 3)."""
        return self._density(self.corners(x))

    def color(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor | None]:
        """rgb (P, 3) and beta raw (P,) (None without the beta head) at points x (P, 3), directions d (P, 3)."""
        return self._color(self.corners(x), self.view_features(d))

    def view_features(self, d: Tensor) -> Tensor:
        """The colour MLP's view-direction input (P, 3 + 6 view_pe): PE(d) of unit directions (no pi), or
        (P, 0) for a view-independent field. Encoded per ray, then gathered for the ray's samples."""
        return posenc(d, self.cfg.view_pe) if self.cfg.view_dependent else d[:, :0]

    def _density(self, corners: tuple[Tensor, Tensor]) -> Tensor:
        return F.softplus(self._lerp(self.density_grid, corners)[:, 0] + self.shift) / self.voxel0

    def _color(self, corners: tuple[Tensor, Tensor], views: Tensor) -> tuple[Tensor, Tensor | None]:
        feat = self._lerp(self.feat_grid, corners)  # (P, C): what the grid holds at the points
        out = self.rgbnet(torch.cat([feat, views], -1))  # views: view_features(d) of the points' rays
        return torch.sigmoid(out[:, :3]), self.beta_raw(feat, out)

    # --- schedule ------------------------------------------------------------------------
    def update_schedule(self, step: int, total_steps: int, step_len: float) -> bool:
        """Coarse-to-fine upsampling, the colour threshold, and the occupancy refresh.

        Returns True when the grids were re-created (upsampled): the optimiser must be rebuilt.
        """
        cfg = self.cfg
        changed = False
        target = sum(1 for a in cfg.upsample_at if step >= a * total_steps)
        while int(self.stage) < target:
            self.stage += 1
            self.upsample(cfg.grid_res[int(self.stage)])
            changed = True
        early = step < cfg.occ_start
        self.color_thresh = self._early_color_thresh() if early else cfg.color_thresh
        if not early and (changed or (step - cfg.occ_start) % cfg.occ_every == 0):
            self.refresh_occupancy(step_len)
        return changed

    @torch.no_grad()
    def refresh_occupancy(self, step_len: float) -> None:
        """occ = dilate(alpha_voxel > min(occ_thresh, occ_rel * max alpha_voxel))."""
        sigma = F.softplus(self.density_grid[..., 0] + self.shift) / self.voxel0  # (Z, Y, X)
        alpha = (1.0 - torch.exp(-sigma * step_len))[None, None]
        thr = min(self.cfg.occ_thresh, self.cfg.occ_rel * float(alpha.max()))
        self.occ = dilate(alpha[0, 0] > thr, self.cfg.occ_dilate).contiguous()
        self._occ_idx = torch.nonzero(self.occ.view(-1)).squeeze(-1)

    @torch.no_grad()
    def upsample(self, res: int) -> None:
        """Trilinear upsampling of the grids to `res` voxels along the longest side."""
        bbox = torch.stack([self.lo, self.hi]).cpu().numpy()
        rx, ry, rz = axis_resolution(bbox, res)
        size = (rz, ry, rx)

        def interp(v: Tensor) -> Tensor:  # (Z, Y, X, C) -> (rz, ry, rx, C)
            v = F.interpolate(v.permute(3, 0, 1, 2)[None], size=size, mode="trilinear", align_corners=True)
            return v[0].permute(1, 2, 3, 0).contiguous()

        self.density_grid = nn.Parameter(interp(self.density_grid.data))
        self.feat_grid = nn.Parameter(interp(self.feat_grid.data))
        occ = interp(self.occ[..., None].float())[..., 0] > 0
        self.occ = occ.contiguous()
        self._occ_idx = None

    def resize_to(self, shape_zyx: tuple[int, int, int]) -> None:
        """Re-create the grids empty at a given (Z,Y,X) shape (used when loading a checkpoint)."""
        dev = self.density_grid.device
        self.density_grid = nn.Parameter(torch.zeros(*shape_zyx, 1, device=dev))
        self.feat_grid = nn.Parameter(torch.zeros(*shape_zyx, self.cfg.feat_dim, device=dev))
        self.occ = torch.ones(*shape_zyx, dtype=torch.bool, device=dev)
        self._occ_idx = None

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in ("density_grid", "feat_grid"):  # runs saved before the grids were channels-last
            v = state_dict.get(prefix + name)
            if v is not None and v.dim() == 5:  # (C, 1, Z, Y, X) -> (Z, Y, X, C)
                state_dict[prefix + name] = v[:, 0].permute(1, 2, 3, 0).contiguous()
        key = prefix + "density_grid"
        if key in state_dict and tuple(state_dict[key].shape) != tuple(self.density_grid.shape):
            self.resize_to(tuple(state_dict[key].shape[:3]))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def regulariser(self) -> Tensor:
        """Total variation, estimated on `tv_samples` random occupied voxels per call.

        TV(V) = mean over voxels and axes of (V[i + e_axis] - V[i])^2, for the density grid
        (weight tv_density) and the feature grids (tv_feat). A full-volume TV of a 128^3 grid
        costs seconds per step on a CPU; this unbiased random subset costs milliseconds.
        """
        c = self.cfg
        r = self.density_grid.new_zeros(())
        if c.tv_density <= 0 and c.tv_feat <= 0:
            return r
        Z, Y, X = self.resolution
        if self._occ_idx is None or self._occ_idx.numel() == 0:
            idx = torch.randint(0, Z * Y * X, (c.tv_samples,), device=self.density_grid.device)
        else:
            pick = torch.randint(0, self._occ_idx.numel(), (c.tv_samples,), device=self._occ_idx.device)
            idx = self._occ_idx[pick]
        z, y, x = idx // (Y * X), (idx // X) % Y, idx % X
        nbrs = [  # the +1 neighbour along each axis (clamped at the far face: difference 0)
            idx + (z < Z - 1).long() * Y * X,
            idx + (y < Y - 1).long() * X,
            idx + (x < X - 1).long(),
        ]

        both = torch.cat([idx] + nbrs)  # one gather per grid

        def tv(v: Tensor) -> Tensor:
            g = gather_rows(v, both).view(4, -1, v.shape[-1])  # (4, n, C)
            return (g[1:] - g[:1]).pow(2).mean() * 3.0  # sum over the 3 axes

        if c.tv_density > 0:
            r = r + c.tv_density * tv(self.density_grid)
        if c.tv_feat > 0:
            r = r + c.tv_feat * tv(self.feat_grid)
        return r

    def make_optimizer(self) -> torch.optim.Optimizer:
        """Adam over the current grids (rebuild it after an upsampling). eps = 1e-15: the default
        1e-8 swamps the grids' tiny early gradients. Each group keeps its base lr in "lr0"."""
        c = self.cfg
        groups = [
            {"params": [self.density_grid], "lr": c.lr_density, "name": "density"},
            {"params": [self.feat_grid], "lr": c.lr_feat, "name": "feat"},
            {"params": list(self.rgbnet.parameters()), "lr": c.lr_mlp, "name": "mlp"},
        ]
        return adam(groups, eps=1e-15, betas=(0.9, 0.99))

    @property
    def resolution(self) -> tuple[int, int, int]:
        """Current grid shape (Z, Y, X)."""
        return tuple(self.density_grid.shape[:3])

    def lattice_shape(self) -> tuple[int, int, int]:
        """(Z, Y, X) of the lattice a point cloud of this field is sampled on: its own voxels."""
        return self.resolution
