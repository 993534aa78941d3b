"""What a run leaves in its folder besides the checkpoint: metrics, test renders, refined poses.

    <run folder>/metrics.json            PSNR / SSIM / LPIPS on the unobserved views (evaluate.py)
    <run folder>/test_renders/<view>.png and <view>_gt.png
    <run folder>/transforms.json         the refined mirrored poses, Blender format, with
    <run folder>/mirrored/<view>.png     their flipped images
    <run folder>/plane.json              --mirror-plane auto: the estimated plane, its confidence
                                         and scores (read back when the run is resumed)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flipviz.data.cameras import Camera
from flipviz.data.images import save_png
from flipviz.files import write_json
from flipviz.geometry.symmetry import PlaneEstimate

PLANE_FILE = "plane.json"


def write_test_renders(run_dir: Path, names: list[str], preds: list[np.ndarray], gts: list[np.ndarray]) -> None:
    for name, pred, gt in zip(names, preds, gts, strict=True):
        save_png(run_dir / "test_renders" / f"{name}.png", pred)
        save_png(run_dir / "test_renders" / f"{name}_gt.png", gt)


def write_metrics(run_dir: Path, metrics: dict) -> Path:
    return write_json(run_dir / "metrics.json", metrics)


def write_transforms(run_dir: Path, cameras: list[Camera], images: list[np.ndarray], image_dir: str = "mirrored") -> Path:
    """Blender-format transforms.json of `cameras` (the refined mirrored poses) + their PNG images."""
    frames = []
    for i, (cam, img) in enumerate(zip(cameras, images, strict=True)):
        rel = f"./{image_dir}/{cam.name or f'mirror_{i:02d}'}"
        save_png(run_dir / (rel + ".png"), img)
        frames.append({"file_path": rel, "transform_matrix": np.asarray(cam.c2w).tolist()})
    data = {"camera_angle_x": float(cameras[0].fov_x) if cameras else 0.0, "frames": frames}
    return write_json(run_dir / "transforms.json", data)


def write_plane(run_dir: Path, estimate: PlaneEstimate) -> Path:
    return write_json(run_dir / PLANE_FILE, estimate.to_dict())
