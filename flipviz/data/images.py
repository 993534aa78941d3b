"""Image conversions and PNG files, in the convention of `flipviz.data.cameras` (float RGB in [0, 1])."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

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


MAX_IMAGE_PIXELS = 2**25  # 33.5 MP (8K UHD is 33.2): a larger image is refused from its header, never decoded


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """(width, height) of an image file from its header alone (Pillow reads no pixel data here); an image
    over MAX_IMAGE_PIXELS (a decompression bomb: 2.6 MB of PNG that decodes to 3.6 GB) is one line."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            with Image.open(path) as im:
                w, h = im.size
        except Image.DecompressionBombError:
            w, h = 0, 0  # beyond Pillow's own bound: refused below with its size unknown
        except (OSError, SyntaxError, ValueError) as e:  # not an image Pillow knows: the decoder says so
            raise DatasetError(f"cannot read {what} {path} ({type(e).__name__})") from None
    if w * h > MAX_IMAGE_PIXELS or w * h == 0:
        size = f"{w}x{h} px" if w * h else "over 179 MP"
        raise DatasetError(
            f"{what} {path} is {size}; flipviz reads images of at most {MAX_IMAGE_PIXELS / 1e6:.1f} MP "
            "(a larger one is refused before it is decoded): downscale it first"
        )
    return w, h


def read_rgba(path: Path) -> np.ndarray:
    """Image file -> float32 (H, W, 4) RGBA in [0, 1] (alpha 1 for RGB files). Its size is checked from the
    header first (image_size); decoding then holds the file's pixels and one float copy, 16 B a pixel."""
    image_size(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        shape = "grayscale" if img.ndim == 2 else f"{img.shape[2]}-channel"
        raise DatasetError(f"image {path} is {shape}; RGB or RGBA images are required")
    scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
    out = np.ones((*img.shape[:2], 4), np.float32)  # alpha 1 unless the file has its own
    c = img.shape[2]
    out[..., :c] = img
    del img
    out[..., :c] /= np.float32(scale)
    out[..., [0, 2]] = out[..., [2, 0]]  # BGR(A) -> RGB(A)
    return out


def composite_on_white(rgba: np.ndarray, width: int | None) -> tuple[np.ndarray, np.ndarray]:
    """RGBA -> (rgb on white, alpha), optionally resized to `width` with area averaging. `rgba` is used up:
    its colour is premultiplied in place (a large image is not copied).

    Resizing is done on the alpha-premultiplied colour (c * a) and on a, then c_white = c*a + 1 - a,
    which is exactly the area average of the composited image.
    """
    premult = rgba
    premult[..., :3] *= rgba[..., 3:4]
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
