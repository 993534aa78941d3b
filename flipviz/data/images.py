"""Image conversions and PNG files, in the convention of `flipviz.data.cameras` (float RGB in [0, 1])."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from flipviz.data.dataset import DatasetError
from flipviz.files import atomic_path


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] (H, W[, C]) -> uint8 RGB (H, W, 3); NaN -> 0; grey maps are repeated."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = (np.clip(np.nan_to_num(img, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    return np.ascontiguousarray(img[..., :3])


def save_png(path: Path | str, img: np.ndarray) -> Path:
    """Write an RGB float (or uint8) image as an 8-bit PNG, atomically."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(to_uint8(img), cv2.COLOR_RGB2BGR)):
            raise DatasetError(f"cannot write {path}")
    return Path(path)
