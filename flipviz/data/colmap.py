"""Read COLMAP sparse models (cameras, images, points3D; .bin or .txt) through pycolmap.

A capture folder holds `images/` and a model in `sparse/0/`, `sparse/` or the folder itself; masks,
when there are any, in `masks/` with the image's name (nerfstudio writes `masks/<name>.png`).
COLMAP's camera frame is OpenCV's (x right, y down, z forward) and its pose world-to-camera; flipviz
turns each into an OpenGL camera-to-world: c2w = inverse(cam_from_world) @ diag(1, -1, -1, 1).
Camera models: the pinhole ones and OpenCV's (OPENCV, RADIAL, SIMPLE_RADIAL), resampled into the
flipviz pinhole by `capture.to_pinhole`. The scene box comes from the sparse points (or the masks).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from flipviz.data.cameras import View
from flipviz.data.capture import Intrinsics, capture_view, make_capture
from flipviz.data.dataset import DatasetError, SceneData
from flipviz.files import inside_folder

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
MODEL_FILES = ("cameras.bin", "cameras.txt")


def find_model(root: Path) -> Path | None:
    """The sparse model folder of a capture: sparse/0, sparse or the folder itself."""
    for d in (root / "sparse" / "0", root / "sparse", root):
        if any((d / f).is_file() for f in MODEL_FILES):
            return d
    return None


def _intrinsics(cam, where: str) -> Intrinsics:
    """pycolmap camera -> Intrinsics (OpenCV distortion order k1, k2, p1, p2)."""
    p = [float(x) for x in cam.params]
    model = cam.model_name
    W, H = int(cam.width), int(cam.height)
    table = {  # model: (fx, fy, cx, cy, distortion) from its parameter list
        "SIMPLE_PINHOLE": lambda: (p[0], p[0], p[1], p[2], ()),
        "PINHOLE": lambda: (p[0], p[1], p[2], p[3], ()),
        "SIMPLE_RADIAL": lambda: (p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0)),
        "RADIAL": lambda: (p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0)),
        "OPENCV": lambda: (p[0], p[1], p[2], p[3], tuple(p[4:8])),
    }
    if model not in table:
        raise DatasetError(f"{where}: COLMAP camera model {model} is not supported (flipviz reads {', '.join(table)})")
    fx, fy, cx, cy, dist = table[model]()
    return Intrinsics(W, H, fx, fy, cx, cy, dist).check(where)


def load_colmap(path: str | os.PathLike, res: int | None = None, images: str = "images") -> SceneData:
    """A COLMAP capture folder (images/ + sparse model) at width `res`."""
    import pycolmap

    root = Path(path)
    model_dir = find_model(root)
    if model_dir is None:
        raise DatasetError(f"no COLMAP model (cameras.bin or cameras.txt) in {root}, {root}/sparse or {root}/sparse/0")
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (ValueError, RuntimeError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise DatasetError(f"COLMAP model {model_dir} is malformed: {msg}") from None
    registered = sorted((im.name, im) for im in rec.images.values() if im.has_pose)
    if not registered:
        raise DatasetError(f"COLMAP model {model_dir} has no registered images")
    image_dir = root / images
    views: dict[int, View] = {}
    for k, (name, im) in enumerate(registered):
        listed_in = f"the COLMAP model {model_dir}"
        in_masks = inside_folder(root / "masks", name, listed_in)
        mask = next((p for p in (in_masks, in_masks.with_suffix(".png")) if os.path.isfile(p)), None)
        intr = _intrinsics(rec.cameras[im.camera_id], f"{model_dir} camera {im.camera_id}")
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c) @ OPENCV_TO_OPENGL
        views[k] = capture_view(inside_folder(image_dir, name, listed_in), mask, intr, c2w, res, k, listed_in)
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else None
    return make_capture(root.name, views, str(root), {}, points, None, {"format": "colmap", "model": str(model_dir)})
