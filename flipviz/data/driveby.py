"""A robot's capture of a built-in scene: a one-sided drive-by, written as a nerfstudio capture.

The robot passes the object on one side: azimuth (about +z, from +x, counter-clockwise) sweeps
`START_DEG` .. `START_DEG + SWEEP_DEG`; its distance and camera height vary along the way; it aims
near, not exactly at, the object (a small wandering look-at offset) and rolls a little. The
held-out views look at the far side from the protocol's height, halfway between the ends of the
sweep and beyond them, and are the capture's `test_filenames`; the drive-by frames are its
`train_filenames`. The object's true mirror plane, when it has one, is written as
`flipviz_symmetry_plane` (read back as the scene's plane, for measurement and `--mirror-plane
scene`). Everything here is generated: nothing is downloaded.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from flipviz.data.builtin import focal_px, render_view, ring_camera
from flipviz.data.cameras import Camera, View, look_at
from flipviz.data.nerfstudio import write_nerfstudio
from flipviz.data.scenes import symmetry_plane

START_DEG, SWEEP_DEG = 60.0, 180.0  # the driven side: azimuths 60..240 degrees
N_DRIVE, N_HELD = 24, 8


def _roll(c2w: np.ndarray, deg: float) -> np.ndarray:
    """Rotate the camera about its own viewing axis by `deg`."""
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out = c2w.copy()
    out[:3, :3] = c2w[:3, :3] @ R
    return out


def driveby_cameras(res: int, n: int = N_DRIVE) -> list[Camera]:
    """The robot's cameras (module docstring), at res x res."""
    s = np.linspace(0.0, 1.0, n)
    cams = []
    for k, t in enumerate(s):
        az = START_DEG + SWEEP_DEG * t
        dist = 4.0 + 0.6 * np.sin(2.0 * np.pi * t)  # closer and farther as it drives
        height = 1.6 + 0.7 * np.sin(3.0 * np.pi * t + 0.5)  # up and down the path
        eye = np.array([dist * np.cos(np.radians(az)), dist * np.sin(np.radians(az)), height])
        target = np.array([0.15 * np.sin(5.0 * t), 0.15 * np.cos(4.0 * t), 0.1 * np.sin(7.0 * t)])  # aims roughly
        c2w = _roll(look_at(eye, target), 4.0 * np.sin(6.0 * t))
        cams.append(Camera(c2w, res, res, focal_px(res), name=f"drive_{k:02d}"))
    return cams


def held_out_cameras(res: int, n: int = N_HELD) -> list[Camera]:
    """Views of the far side (azimuths beyond the sweep) from the orbit's ring, at the centre."""
    return [ring_camera(START_DEG + SWEEP_DEG + (360.0 - SWEEP_DEG) * (k + 0.5) / n, res, f"far_{k}") for k in range(n)]


def export_driveby(name: str, out_dir: str | os.PathLike, res: int = 100) -> Path:
    """Write built-in scene `name` as a nerfstudio capture along the drive-by, plus far-side views."""
    cams = driveby_cameras(res) + held_out_cameras(res)
    views = [View(c, *render_view(name, c), index=k) for k, c in enumerate(cams)]
    drive = list(range(N_DRIVE))
    held = list(range(N_DRIVE, N_DRIVE + N_HELD))
    extra = {"flipviz_scene": name, "trajectory": "driveby"}
    plane = symmetry_plane(name)
    if plane is not None:  # known for measurement only: nothing in training reads it
        extra["flipviz_symmetry_plane"] = plane.to_dict()
    return write_nerfstudio(views, out_dir, {"train": drive, "test": held}, extra)
