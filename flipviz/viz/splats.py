"""The field as Gaussian splats: one Gaussian per baked cell, drawn and sorted by the browser's WebGL.

`Trainer.point_cloud` bakes the field's lattice cells with their colour and their opacity over one
cell, alpha = 1 - exp(-sigma * cell). A cell becomes a Gaussian centred on it:

    Sigma   = (SIGMA_PER_CELL * cell)^2 I        covariance: neighbouring cells overlap and blend
    opacity = max(alpha, floor)                 peak opacity; floor > 0 keeps colour-mapped cells readable

so a surface reads as a surface, not as a staircase of squares. viser packs a splat into 32 bytes
(float32 centre, float16 covariance, uint8 RGBA); Rerun logs the same splats (`GaussianSplats3D`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flipviz.data.images import to_uint8

SIGMA_PER_CELL = 0.6  # standard deviation of a cell's Gaussian, in cells: at 0.5 cells neighbours barely touch
VISER_BYTES = 32  # per splat in viser's GaussianSplatsMessage


@dataclass(frozen=True)
class Splats:
    centers: np.ndarray  # (N, 3) float32
    sigma: float  # the standard deviation of every Gaussian, world units
    rgbs: np.ndarray  # (N, 3) uint8
    opacities: np.ndarray  # (N,) float32 in [0, 1]

    def __len__(self) -> int:
        return len(self.centers)

    @property
    def covariances(self) -> np.ndarray:
        """(N, 3, 3) float32: sigma^2 I for every splat."""
        return np.broadcast_to(np.eye(3, dtype=np.float32) * np.float32(self.sigma**2), (len(self), 3, 3))

    @property
    def nbytes(self) -> int:
        """What one browser receives for them (viser's packing)."""
        return VISER_BYTES * len(self)


def cells_to_splats(points: np.ndarray, rgbs: np.ndarray, alpha: np.ndarray, cell: float, floor: float = 0.0) -> Splats:
    """Splats of baked cells: centres `points` (N, 3), colours `rgbs` (N, 3) uint8, per-cell opacity
    `alpha` (N,), lattice spacing `cell`; `floor`: the least opacity drawn (for colour-mapped views)."""
    opacity = np.clip(np.maximum(np.asarray(alpha, np.float32), floor), 0.0, 1.0)
    return Splats(np.asarray(points, np.float32), SIGMA_PER_CELL * float(cell), np.asarray(rgbs, np.uint8), opacity)


def solid_splats(baked: dict) -> Splats:
    """The solid cells of a bake (`Trainer.point_cloud`) in their own colours and opacities."""
    solid = baked["solid"]
    rgb = to_uint8(baked["rgb"][solid][:, None, :])[:, 0]  # (N, 3) uint8
    return cells_to_splats(baked["points"][solid], rgb, baked["alpha"][solid], float(baked["cell"]))
