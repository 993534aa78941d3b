"""How well the mirrored cameras cover the unobserved test views: per test view, the angle (about the
object's centre) to the nearest mirrored camera, and the share of test views within 30 degrees.

A test view near a mirrored camera sees what that flipped image claims; one far from every mirror
(on the protocol's ring: half-way between two mirrors, or where mirrors pile up elsewhere) gets
nothing from flipping. The bench puts this beside each configuration's gain Flip+U - B/L.
"""

from __future__ import annotations

import numpy as np

from flipviz.data.cameras import Camera

NEAR_DEG = 30.0  # "covered": a mirrored camera within this angle of the test view


def nearest_mirror_deg(tests: list[Camera], mirrors: list[Camera], center: np.ndarray) -> np.ndarray:
    """(T,) angle in degrees between each test camera's direction from `center` and the nearest
    mirrored camera's (inf when there are no mirrors)."""
    if not mirrors:
        return np.full(len(tests), np.inf)
    unit = lambda cams: np.stack([(c.center - center) / np.linalg.norm(c.center - center) for c in cams])  # noqa: E731
    cos = np.clip(unit(tests) @ unit(mirrors).T, -1.0, 1.0)  # (T, M)
    return np.degrees(np.arccos(cos.max(axis=1)))


def coverage(tests: list[Camera], mirrors: list[Camera], center: np.ndarray) -> dict:
    """mean_angle_deg, max_angle_deg, within_30 (share of test views), per_view_deg."""
    a = nearest_mirror_deg(tests, mirrors, np.asarray(center, dtype=np.float64))
    return {
        "mean_angle_deg": float(a.mean()),
        "max_angle_deg": float(a.max()),
        f"within_{NEAR_DEG:.0f}": float((a <= NEAR_DEG).mean()),
        "per_view_deg": a.tolist(),
    }
