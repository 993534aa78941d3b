"""Least-squares sphere through the input camera centres (paper Sec. IV-A, "Initial Camera Pose").

The paper writes the sphere with centre (x0, y0, z0) and radius r as
    x^2 + y^2 + z^2 = 2x x0 + 2y y0 + 2z z0 + (r^2 - x0^2 - y0^2 - z0^2),
one row per camera centre, i.e. the linear system f = A c with
    A = [2x, 2y, 2z, 1],  f = x^2 + y^2 + z^2,  c = (x0, y0, z0, r^2 - |centre|^2),
and takes c' = argmin_c |A c - f|^2.

Degenerate input. The system has a unique solution only when the centres are not coplanar.
Cameras on a ring at one elevation (the protocol's built-in scenes) ARE coplanar: every sphere
through their circle fits equally well, a one-parameter family whose centres lie on the circle's
axis. Choosing the circle's own centre (the minimum-|centre - centroid| least-squares solution)
puts the look-at target above the object for a ring above the equator. flipviz instead picks,
along that axis, the point closest to where the cameras look: the least-squares intersection of
their optical axes. That point is the object centre for the usual "cameras look at the object"
capture, so the sphere's centre is the right look-at target for the mirrored cameras. Without
viewing directions the circle's centre is returned (documented fallback).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from flipviz.data.cameras import Camera, axes_intersection
from flipviz.data.dataset import DatasetError


@dataclass(frozen=True)
class Sphere:
    """A sphere with `center` (3,) and `radius` (world units)."""

    center: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", np.asarray(self.center, dtype=np.float64).reshape(3))
        object.__setattr__(self, "radius", float(self.radius))

    def to_dict(self) -> dict:
        return {"center": self.center.tolist(), "radius": self.radius}


def _as_points(points: np.ndarray, what: str = "points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DatasetError(f"sphere fit: {what} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DatasetError(f"sphere fit: {what} contain NaN or infinite values")
    return p


def fit_sphere(points: np.ndarray, view_dirs: np.ndarray | None = None, planar_tol: float = 1e-3) -> Sphere:
    """Sphere through `points` (N >= 4, (N, 3)) by the paper's linear least squares f = A c.

    If the points are (nearly) coplanar (smallest principal extent < `planar_tol` x largest) the
    sphere is not unique. Then the circle through them is fitted in their plane (same f = A c,
    in 2D) and the centre is chosen on the circle's axis: at the foot of the least-squares
    intersection of the `view_dirs` (the cameras' viewing directions, (N, 3)) when given and not
    parallel, else at the circle's centre. The radius is the algebraic least-squares radius for
    that centre, r^2 = mean |p - centre|^2. `view_dirs` is ignored for non-coplanar points.
    Collinear, coincident or fewer than 4 points raise DatasetError.
    """
    p = _as_points(points)
    if len(p) < 4:
        raise DatasetError(f"sphere fit needs at least 4 camera centres, got {len(p)}")
    g = p.mean(0)
    _, s, Vt = np.linalg.svd(p - g, full_matrices=False)
    if s[0] < 1e-9 * max(1.0, float(np.abs(p).max())):
        raise DatasetError("sphere fit: all camera centres coincide")
    if s[1] < 1e-6 * s[0]:
        raise DatasetError("sphere fit: camera centres are collinear, no sphere passes through them")

    if s[2] >= planar_tol * s[0]:
        # Paper: x^2+y^2+z^2 = 2x x0 + 2y y0 + 2z z0 + (r^2 - x0^2 - y0^2 - z0^2), solve f = A c.
        q = p - g  # centred for conditioning (same minimiser, reparametrised); translated back below
        A = np.concatenate([2.0 * q, np.ones((len(q), 1))], axis=1)
        f = (q**2).sum(1)
        c, *_ = np.linalg.lstsq(A, f, rcond=None)
        center = g + c[:3]
        r2 = c[3] + (c[:3] ** 2).sum()
        return Sphere(center, float(np.sqrt(max(r2, 0.0))))

    # Coplanar: the same f = A c in the plane's 2D coordinates gives the circle (centre, radius).
    e, n = Vt[:2], Vt[2]
    uv = (p - g) @ e.T
    A = np.concatenate([2.0 * uv, np.ones((len(uv), 1))], axis=1)
    c, *_ = np.linalg.lstsq(A, (uv**2).sum(1), rcond=None)
    circle_center = g + c[:2] @ e
    center = circle_center
    if view_dirs is not None:
        target = axes_intersection(p, _as_points(view_dirs, "view directions"))
        if target is not None:
            center = circle_center + float(n @ (target - circle_center)) * n  # on the circle's axis
    radius = float(np.sqrt(((p - center) ** 2).sum(1).mean()))
    return Sphere(center, radius)


def view_direction(cam: Camera) -> np.ndarray:
    """The camera's viewing direction in world coordinates (OpenGL: it looks along -z)."""
    return -cam.c2w[:3, 2]


def fit_camera_sphere(cameras: Sequence[Camera], planar_tol: float = 1e-3) -> Sphere:
    """Paper Sec. IV-A: the least-squares sphere through the camera centres (axes break ties)."""
    if len(cameras) == 0:
        raise DatasetError("sphere fit: no cameras")
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([view_direction(c) for c in cameras])
    return fit_sphere(centers, dirs, planar_tol=planar_tol)
