"""The one camera convention of flipviz. Every module uses it; nothing converts.

World frame: right-handed, +z up (as in Blender and the NeRF-synthetic scenes); objects sit
near the origin inside roughly [-1.5, 1.5]^3.

Camera frame: OpenGL / Blender, as stored in `transforms_*.json`: `c2w` is a 4x4
camera-to-world matrix whose rotation columns are the camera's +x (right), +y (up) and +z
(backwards: the camera looks along -z) axes in world coordinates; its last column is the
camera centre.

Intrinsics: ideal pinhole, square pixels, fx = fy = `focal` (pixels), principal point at the
image centre. Pixel (u, v) (u = column to the right, v = row downwards) has its centre at
(u + 0.5, v + 0.5). The camera-frame ray through it is
    d_cam = ((u + 0.5 - W/2) / f, -(v + 0.5 - H/2) / f, -1).

Images: float32 RGB in [0, 1], shape (H, W, 3), composited on a white background; alpha, where
known, is float32 (H, W) in [0, 1].

A horizontal image flip (u -> W-1-u) is exactly the image of the camera whose x axis is negated
(an improper "camera"); see `flipviz.geometry.mirror` for how a proper mirrored pose is built.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch


@dataclass(frozen=True)
class Camera:
    """A posed pinhole camera in the flipviz convention (see module docstring)."""

    c2w: np.ndarray  # (4, 4) float64, camera-to-world, OpenGL axes
    width: int
    height: int
    focal: float  # pixels
    name: str = ""

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
        if c2w.shape != (4, 4):
            raise ValueError(f"camera {self.name!r}: c2w must be 4x4 or 3x4, got {c2w.shape}")
        object.__setattr__(self, "c2w", c2w)

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    @property
    def rotation(self) -> np.ndarray:
        return self.c2w[:3, :3].copy()

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsics for a y-down image (OpenCV/Rerun/viser style pixel coordinates)."""
        return np.array([[self.focal, 0.0, self.width / 2.0], [0.0, self.focal, self.height / 2.0], [0.0, 0.0, 1.0]])

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians."""
        return 2.0 * float(np.arctan(0.5 * self.height / self.focal))

    @property
    def fov_x(self) -> float:
        return 2.0 * float(np.arctan(0.5 * self.width / self.focal))

    def with_pose(self, c2w: np.ndarray, name: str | None = None) -> Camera:
        return replace(self, c2w=np.asarray(c2w, dtype=np.float64), name=self.name if name is None else name)

    def resized(self, width: int, height: int | None = None) -> Camera:
        """Same pose and field of view, another resolution."""
        height = round(self.height * width / self.width) if height is None else height
        return replace(self, width=int(width), height=int(height), focal=self.focal * width / self.width)

    def cropped(self, width: int) -> Camera:
        """The centre `width` columns of this view: same pose, focal and height."""
        return replace(self, width=int(width))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (P, 3) -> integer pixel (row, column) (P, 2), and (P,) bool: in front of the
        camera and inside the image. Rows and columns are valid only where the flag is set."""
        p = (np.asarray(points, dtype=np.float64) - self.center) @ self.rotation  # camera frame, looks along -z
        z = np.maximum(-p[:, 2], 1e-9)
        u = self.focal * p[:, 0] / z + self.width / 2
        r = -self.focal * p[:, 1] / z + self.height / 2
        inside = (-p[:, 2] > 1e-6) & (u >= 0) & (u < self.width) & (r >= 0) & (r < self.height)
        return r.astype(int), u.astype(int), inside

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space ray origins and unit directions, (H*W, 3) float32 each, row-major pixels."""
        d = pixel_directions(self.width, self.height, self.focal) @ self.c2w[:3, :3].T.astype(np.float32)
        d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        o = np.repeat(self.c2w[None, :3, 3].astype(np.float32), len(d), axis=0)
        return o, d


def pixel_directions(width: int, height: int, focal: float) -> np.ndarray:
    """Camera-frame (unnormalised, z = -1) ray directions through pixel centres, (H*W, 3) float32.

    x and y are exact negatives for mirror-image pixels (u and W-1-u), so image flips stay exact.
    """
    d = np.empty((height, width, 3), np.float32)
    d[..., 0] = ((np.arange(width) + 0.5 - width / 2.0) / focal)[None, :]
    d[..., 1] = (-(np.arange(height) + 0.5 - height / 2.0) / focal)[:, None]
    d[..., 2] = -1.0
    return d.reshape(-1, 3)


def rays_from_c2w(c2w: torch.Tensor, dirs_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable ray generation: c2w (..., 3 or 4, 4), dirs_cam (..., 3) -> origins, unit dirs.

    Broadcasts over leading dimensions, so per-ray poses (N, 4, 4) with per-ray camera-frame
    directions (N, 3) work, which is what pose refinement needs.
    """
    R = c2w[..., :3, :3]
    d = (R @ dirs_cam.unsqueeze(-1)).squeeze(-1)
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[..., :3, 3].expand_as(d)
    return o, d


def axes_intersection(points: np.ndarray, view_dirs: np.ndarray) -> np.ndarray | None:
    """Least-squares point closest to all lines p_i + t d_i: argmin_q sum |(I - d d^T)(q - p_i)|^2.

    Returns None when the lines are (nearly) parallel, so that no such point is determined.
    """
    p, d = np.asarray(points, dtype=np.float64), np.asarray(view_dirs, dtype=np.float64)
    if p.shape != d.shape or p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"axes_intersection: {d.shape} view directions for points {p.shape}")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors orthogonal to each axis
    M, b = P.sum(0), (P @ p[:, :, None]).sum(0)[:, 0]
    s = np.linalg.svd(M, compute_uv=False)
    if s[-1] < 1e-6 * s[0]:
        return None
    return np.linalg.solve(M, b)


def looked_at_point(cameras: list[Camera]) -> np.ndarray | None:
    """Where a set of cameras looks: the least-squares meeting point of their optical axes."""
    return axes_intersection(np.stack([c.center for c in cameras]), np.stack([-c.c2w[:3, 2] for c in cameras]))


WORLD_UP = np.array([0.0, 0.0, 1.0])


def horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (u, v) orthogonal to `up`, (u, v, up) right-handed: u is the world x axis made
    horizontal (y when x is up); azimuths about `up` are counted from u towards v."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    ref = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[1]
    u = ref - (ref @ up) * up
    u /= np.linalg.norm(u)
    return u, np.cross(up, u)


def azimuth_deg(vector: np.ndarray, up: np.ndarray) -> float:
    """Azimuth of `vector` about `up`, degrees in [0, 360), counted from u towards v of `horizontal_basis`."""
    u, v = horizontal_basis(up)
    return float(np.degrees(np.arctan2(vector @ v, vector @ u)) % 360.0)


def unit_vector(v: np.ndarray, what: str) -> np.ndarray:
    """v / |v| as float64 (3,); ValueError naming `what` when v is zero or not finite."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"{what} must be a non-zero finite vector, got {v.tolist()}")
    return v / n


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """Paper Sec. IV-A: rotation from (c, at, up); c2w (4, 4) OpenGL, the camera looks at `target`.

    z = normalize(eye - target), x = normalize(up x z), y = z x x. When `up` is parallel to the
    viewing direction (camera straight above or below the target) x is taken along the world axis
    least aligned with z, projected off z, so a proper pose is still returned.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    z = unit_vector(eye - np.asarray(target, dtype=np.float64).reshape(3), "look_at: eye - target")
    x = np.cross(unit_vector(up, "look_at: up"), z)
    if np.linalg.norm(x) < 1e-9:  # up parallel to the view axis: any horizontal x will do
        a = np.eye(3)[int(np.argmin(np.abs(z)))]
        x = a - (a @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


@dataclass
class View:
    """One image with its camera. `index` is its position on the source orbit (see protocol)."""

    camera: Camera
    rgb: np.ndarray  # (H, W, 3) float32 on white
    alpha: np.ndarray | None = None  # (H, W) float32, None when unknown
    index: int = -1
    meta: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.camera.name
