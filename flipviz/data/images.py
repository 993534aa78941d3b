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


def read_rgba(path: Path) -> np.ndarray:
    """Image file -> float32 (H, W, 4) RGBA in [0, 1] (alpha 1 for RGB files)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        shape = "grayscale" if img.ndim == 2 else f"{img.shape[2]}-channel"
        raise DatasetError(f"image {path} is {shape}; RGB or RGBA images are required")
    scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
    img = img.astype(np.float32) / scale
    if img.shape[2] == 3:
        return np.concatenate([cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.ones_like(img[..., :1])], axis=-1)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)


def composite_on_white(rgba: np.ndarray, width: int | None) -> tuple[np.ndarray, np.ndarray]:
    """RGBA -> (rgb on white, alpha), optionally resized to `width` with area averaging.

    Resizing is done on the alpha-premultiplied colour (c * a) and on a, then c_white = c*a + 1 - a,
    which is exactly the area average of the composited image.
    """
    a = rgba[..., 3:4]
    premult = np.concatenate([rgba[..., :3] * a, a], axis=-1)
    H, W = rgba.shape[:2]
    if width is not None and width != W:
        height = max(1, round(H * width / W))
        premult = cv2.resize(premult, (width, height), interpolation=cv2.INTER_AREA)
    a = np.clip(premult[..., 3], 0.0, 1.0)
    rgb = np.clip(premult[..., :3] + (1.0 - a[..., None]), 0.0, 1.0)
    return rgb.astype(np.float32), a.astype(np.float32)


def uncomposite(rgb: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    """(rgb on white, alpha) -> uint8 RGBA: c = (c_white - 1 + a) / a where a > 0 (inverse of the above)."""
    a = np.ones(rgb.shape[:2], np.float32) if alpha is None else alpha
    c = np.where(a[..., None] > 0, (rgb - 1.0 + a[..., None]) / np.maximum(a[..., None], 1e-8), 0.0)
    return np.round(np.concatenate([np.clip(c, 0, 1), a[..., None]], axis=-1) * 255.0).astype(np.uint8)


def save_rgba_png(path: Path | str, rgba: np.ndarray) -> Path:
    """Write a uint8 RGBA image as a PNG, atomically."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)):
            raise DatasetError(f"cannot write {path}")
    return Path(path)
