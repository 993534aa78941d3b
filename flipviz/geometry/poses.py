"""Camera poses in the flipviz convention (OpenGL camera-to-world, z-up world): look-at, errors,
proper-rotation checks and plane reflections."""

from __future__ import annotations

import numpy as np

from flipviz.data.cameras import look_at, unit_vector  # noqa: F401  (look_at: the paper's pose step)


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
    n = unit_vector(normal, "reflection normal")
    return np.eye(3) - 2.0 * np.outer(n, n)
