"""A radiance field + the volume renderer + the opacity-entropy regulariser, on one device.

    model = RadianceModel(ModelConfig(), scene.bbox, scene.near, scene.far, with_beta=True)
    opt = model.make_optimizer()
    for step in range(total_steps):
        if model.update_schedule(step, total_steps):   # the field re-created its parameters
            opt = model.make_optimizer()                # (grid upsampled): new Adam state
        model.adjust_lr(opt, step, total_steps)
        out = model.render_rays(origins, dirs, training=True)    # rgb (R,3), beta2 (R,), ...
        loss = <objective>(out, target) + model.regulariser()
        opt.zero_grad(); loss.backward(); opt.step()

The field (`GridConfig` or `NerfConfig`, each with its own knobs) owns its schedule and optimiser
settings; the model adds what every field shares: ray sampling and the beta^2 compositing settings.
`state_dict()` / `load_state_dict()` round-trip exactly (grid resolution and occupancy mask
included) into a fresh model of the same config.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor, nn

from flipviz.data.cameras import Camera
from flipviz.model.grid_field import GridConfig
from flipviz.model.nerf_field import NerfConfig
from flipviz.model.optim import decay_lr
from flipviz.model.renderer import render_rays


class RenderCancelled(Exception):
    """A render stopped between its chunks of rays: the run was asked to stop (render_image's `cancel`)."""


@dataclass
class ModelConfig:
    field: GridConfig | NerfConfig = field(default_factory=GridConfig)
    """GridConfig: dense voxel grid (fast, default); NerfConfig: vanilla NeRF MLP (the paper's)."""
    n_samples: int = 64
    """Samples per ray inside the scene box (training and rendering)."""
    beta_min: float = 0.1
    """beta_bar^2 = beta_min^2 + softplus(raw) (Sec. IV-C)."""
    beta_init: float = 0.1
    """Initial per-sample softplus(raw) = beta_init^2."""
    beta2_mode: Literal["linear", "variance"] = "linear"
    """Compositing of beta_bar^2: linear sum w beta^2 (official code) or sum w^2 beta^2."""
    w_entropy: float = 1e-3
    """Weight of the opacity-entropy term (DVGO's weight_entropy_last): pushes every ray to be
    fully opaque or fully transparent, which removes the white fog a white background allows."""
    background: Literal["white", "learned", "last"] = "white"
    """What a ray's unspent weight sees (renderer.py): white, one learned colour, or the field's
    colour at the ray's far end (the official code)."""
    beta_from: Literal["colour", "position"] = "colour"
    """The variance head on the colour branch, or on the position features alone (the official code)."""
    background_lr: float = 0.1
    """Adam learning rate of the learned background colour (its logit)."""


class RadianceModel(nn.Module):
    def __init__(
        self,
        cfg: ModelConfig,
        bbox: np.ndarray,
        near: float,
        far: float,
        with_beta: bool,
        device: torch.device | str = "cpu",
    ):
        super().__init__()
        bbox = np.asarray(bbox, dtype=np.float64)
        if bbox.shape != (2, 3) or not np.all(bbox[1] > bbox[0]):
            raise ValueError(f"bbox must be (2,3) with max > min, got {bbox.tolist()}")
        if not 0.0 <= near < far:
            raise ValueError(f"need 0 <= near < far, got near={near}, far={far}")
        self.cfg = cfg
        self.near, self.far, self.with_beta = float(near), float(far), bool(with_beta)
        self.device = torch.device(device)
        self.register_buffer("bbox", torch.as_tensor(bbox, dtype=torch.float32, device=self.device))
        self.field = cfg.field.build(bbox, self.with_beta, cfg.beta_init, self.device, cfg.beta_from)
        if cfg.background == "learned":  # one RGB colour, sigmoid(logit); starts near white
            self.background_logit = nn.Parameter(torch.full((3,), 3.0, device=self.device))
        self._pending_opacity: list[Tensor] = []

    def background_rgb(self) -> Tensor | None:
        """The learned background colour (3,), or None (white or last)."""
        return torch.sigmoid(self.background_logit) if self.cfg.background == "learned" else None

    # --- rendering -----------------------------------------------------------------------
    def render_rays(self, origins: Tensor, dirs: Tensor, *, training: bool) -> dict[str, Tensor]:
        """rgb (R,3) on the background, depth (R,), opacity (R,), sigma_mean (R,), beta2 (R,) if with_beta.

        With training=True, samples are jittered and the batch's opacities are remembered for
        the entropy term of the next `regulariser()` call.
        """
        out = render_rays(
            self.field,
            origins,
            dirs,
            bbox=self.bbox,
            near=self.near,
            far=self.far,
            n_samples=self.cfg.n_samples,
            training=training,
            beta_min=self.cfg.beta_min,
            beta2_mode=self.cfg.beta2_mode,
            background=self.cfg.background,
            background_rgb=self.background_rgb(),
        )
        if training and self.cfg.w_entropy > 0 and torch.is_grad_enabled():
            self._pending_opacity = self._pending_opacity[-15:] + [out["opacity"]]  # bounded
        return out

    @torch.no_grad()
    def render_image(
        self, camera: Camera, chunk: int = 16384, cancel: Callable[[], bool] | None = None
    ) -> dict[str, np.ndarray]:
        """Render a whole image (no grad): rgb (H,W,3), depth, opacity (and beta2) (H,W) float32. `cancel` is
        asked before each chunk of rays: True raises RenderCancelled (a NeRF view on a CPU takes minutes)."""
        o, d = (torch.from_numpy(a).to(self.device) for a in camera.rays())
        parts: dict[str, list[Tensor]] = {}
        for i in range(0, o.shape[0], chunk):
            if cancel is not None and cancel():
                raise RenderCancelled(f"{camera.name}: stopped after {i} of {o.shape[0]} rays")
            for k, v in self.render_rays(o[i : i + chunk], d[i : i + chunk], training=False).items():
                parts.setdefault(k, []).append(v)
        shape = (camera.height, camera.width)
        return {
            k: torch.cat(v).float().cpu().numpy().reshape(shape + v[0].shape[1:])  # (H, W, 3) or (H, W)
            for k, v in parts.items()
            if k != "sigma_mean"
        }

    @torch.no_grad()
    def point_cloud(
        self,
        min_alpha: float = 0.05,
        max_points: int = 150_000,
        faint_alpha: float = 0.005,
        max_faint: int = 30_000,
        chunk: int = 65536,
    ) -> dict[str, np.ndarray]:
        """The field as coloured points, for a live 3D preview.

        Points are lattice cells (the grid's own voxels; 48^3 for the MLP) with their opacity over
        one cell, alpha = 1 - exp(-sigma * cell). `solid` cells (alpha > min_alpha, the `max_points`
        most opaque) carry rgb (mean over four horizontal view directions). With a beta head, the
        faint cells (faint_alpha < alpha <= min_alpha) whose per-cell variance is highest are added
        too (`max_faint` of them): a faint structure the model keeps uncertain, such as the ghost
        of a mirrored handle, is where beta^2 lights up. Returns points (P, 3), rgb (P, 3),
        alpha (P,), solid (P,) bool, beta2 (P,) = beta_min^2 + softplus(raw) (with a beta head),
        and cell: the cell size.
        """
        Z, Y, X = self.field.lattice_shape()
        lo, hi = self.bbox[0], self.bbox[1]
        axes = [torch.linspace(float(lo[i]), float(hi[i]), n, device=self.device) for i, n in enumerate((X, Y, Z))]
        zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        pts = torch.stack([xx, yy, zz], -1).reshape(-1, 3)  # (Z Y X, 3)
        cell = float(((hi - lo) / torch.tensor([X - 1, Y - 1, Z - 1], device=self.device)).max())
        sigma = torch.cat([self.field.density(pts[i : i + chunk]) for i in range(0, len(pts), chunk)])
        alpha = 1.0 - torch.exp(-sigma * cell)
        solid = torch.nonzero(alpha > min_alpha).squeeze(-1)
        if solid.numel() > max_points:
            solid = solid[torch.topk(alpha[solid], max_points).indices]
        dirs = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]], device=self.device)
        rgb, raw = self._colour(pts[solid], dirs, chunk)
        keep, solid_flag = solid, torch.ones(len(solid), dtype=torch.bool, device=self.device)
        if self.with_beta and max_faint > 0:
            faint = torch.nonzero((alpha > faint_alpha) & (alpha <= min_alpha)).squeeze(-1)
            if len(faint) > 3 * max_faint:  # a random share keeps the bake fast; the structure shows
                pick = torch.randperm(len(faint), generator=torch.Generator().manual_seed(0))[: 3 * max_faint]
                faint = faint[pick.to(faint.device)]
            f_rgb, f_raw = self._colour(pts[faint], dirs[:1], chunk)  # one direction: a cheap first look
            top = torch.topk(f_raw, min(max_faint, len(faint))).indices
            keep = torch.cat([solid, faint[top]])
            rgb, raw = torch.cat([rgb, f_rgb[top]]), torch.cat([raw, f_raw[top]])
            solid_flag = torch.cat([solid_flag, torch.zeros(len(top), dtype=torch.bool, device=self.device)])
        out = {"points": pts[keep], "rgb": rgb, "alpha": alpha[keep], "solid": solid_flag}
        if self.with_beta:
            out["beta2"] = self.cfg.beta_min**2 + torch.nn.functional.softplus(raw)
        res = {k: v.cpu().numpy() if v.dtype == torch.bool else v.float().cpu().numpy() for k, v in out.items()}
        res["cell"] = np.float32(cell)
        return res

    def _colour(self, p: Tensor, dirs: Tensor, chunk: int) -> tuple[Tensor, Tensor]:
        """rgb (P, 3) and beta raw (P,) of points p, averaged over the view directions `dirs`."""
        rgb = torch.zeros(len(p), 3, device=self.device)
        raw = torch.zeros(len(p), device=self.device)
        for d in dirs:
            for i in range(0, len(p), chunk):
                c, r = self.field.color(p[i : i + chunk], d.expand(len(p[i : i + chunk]), 3))
                rgb[i : i + chunk] += c / len(dirs)
                if r is not None:
                    raw[i : i + chunk] += r / len(dirs)
        return rgb, raw

    # --- optimisation --------------------------------------------------------------------
    def make_optimizer(self) -> torch.optim.Optimizer:
        """The field's optimiser over its current parameters (rebuild it when update_schedule says so),
        and the learned background's group."""
        opt = self.field.make_optimizer()
        if self.cfg.background == "learned":
            lr = self.cfg.background_lr
            opt.add_param_group({"params": [self.background_logit], "lr": lr, "lr0": lr, "name": "background"})
        return opt

    def adjust_lr(self, optimizer: torch.optim.Optimizer, step: int, total_steps: int) -> None:
        """Exponential decay lr0 -> lr0 * lr_decay over training."""
        decay_lr(optimizer, step, total_steps, self.cfg.field.lr_decay)

    def update_schedule(self, step: int, total_steps: int) -> bool:
        """The field's schedule (call every step, before rendering). True: its parameters are new."""
        return self.field.update_schedule(step, total_steps, self.sample_spacing())

    def sample_spacing(self) -> float:
        """Typical distance between samples: the box diagonal over n_samples."""
        return float((self.bbox[1] - self.bbox[0]).norm()) / self.cfg.n_samples

    def regulariser(self) -> Tensor:
        """Already weighted: the field's own (TV on the grids; none for the NeRF MLP) plus
        w_entropy * mean binary entropy of the opacities of the rays rendered with training=True
        since the last call (add it once per optimisation step)."""
        r = self.field.regulariser()
        if self._pending_opacity:
            a = torch.cat(self._pending_opacity).clamp(1e-6, 1 - 1e-6)
            self._pending_opacity = []
            r = r + self.cfg.w_entropy * (-(a * torch.log(a) + (1 - a) * torch.log(1 - a))).mean()
        return r
