"""Camera poses in the flipviz convention (OpenGL camera-to-world, z-up world): look-at, errors,
proper-rotation checks and plane reflections."""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray, what: str) -> np.ndarray:
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
    z = _unit(eye - np.asarray(target, dtype=np.float64).reshape(3), "look_at: eye - target")
    x = np.cross(_unit(up, "look_at: up"), z)
    if np.linalg.norm(x) < 1e-9:  # up parallel to the view axis: any horizontal x will do
        a = np.eye(3)[int(np.argmin(np.abs(z)))]
        x = a - (a @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees: theta = 2 asin(|R1 - R2|_F / (2 sqrt 2))."""
    d = np.linalg.norm(np.asarray(R1, dtype=np.float64)[:3, :3] - np.asarray(R2, dtype=np.float64)[:3, :3])
    return float(np.degrees(2.0 * np.arcsin(min(1.0, d / (2.0 * np.sqrt(2.0))))))


def pose_errors(c2w_a: np.ndarray, c2w_b: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error = distance between the camera centres)."""
    a, b = np.asarray(c2w_a, dtype=np.float64), np.asarray(c2w_b, dtype=np.float64)
    return rotation_angle_deg(a[:3, :3], b[:3, :3]), float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


def is_proper_rotation(R: np.ndarray, atol: float = 1e-6) -> bool:
    """R^T R = I and det R = +1 (a rotation, not a reflection)."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=atol) and abs(np.linalg.det(R) - 1.0) < atol)


def reflection_matrix(normal: np.ndarray) -> np.ndarray:
    """Householder reflection M = I - 2 n n^T about the plane with normal n through the origin."""
    n = _unit(normal, "reflection normal")
    return np.eye(3) - 2.0 * np.outer(n, n)
