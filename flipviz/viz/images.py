"""Images the app, the video and the report share: thumbnails, scalar maps (depth, opacity, beta^2),
error maps, and the view-axis depth a background image is composited with. No viser here."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flipviz.data.cameras import Camera, pixel_directions
from flipviz.data.images import to_uint8
from flipviz.viz import palette


def thumbnail(img: np.ndarray, max_side: int = 64) -> np.ndarray:
    """uint8 thumbnail by integer striding (cheap; thumbnails are only for frustums)."""
    img = to_uint8(img)
    step = max(1, int(math.ceil(max(img.shape[:2]) / max_side)))
    return np.ascontiguousarray(img[::step, ::step])


def upscale(img: np.ndarray, min_side: int = 128) -> np.ndarray:
    """Nearest-neighbour upscaling of a small uint8 image, so the browser shows crisp pixels."""
    k = max(1, int(math.ceil(min_side / max(1, min(img.shape[:2])))))
    return np.ascontiguousarray(img.repeat(k, 0).repeat(k, 1)) if k > 1 else img


OUTPUTS: tuple[str, ...] = ("RGB", "depth", "opacity", "beta^2")
OUTPUT_KEY = {"RGB": "rgb", "depth": "depth", "opacity": "opacity", "beta^2": "beta2"}


@dataclass(frozen=True)
class ScalarView:
    """How a scalar output is shown: its fixed range (or per frame) and the label of its colour bar."""

    depth_range: tuple[float, float] = (2.0, 6.0)  # world units along the view axis
    per_frame: bool = False  # beta^2 on this frame's 1st..99th percentile instead of BETA2_RANGE


def output_range(out: dict, which: str, view: ScalarView) -> tuple[float, float, str] | None:
    """(lo, hi, label) of the colour scale of `which` (None for RGB)."""
    if which == "depth":
        return (*view.depth_range, "depth (world units)")
    if which == "opacity":
        return (*palette.OPACITY_RANGE, "opacity")
    if which == "beta^2":
        b = out.get("beta2")
        if view.per_frame and b is not None:
            lo, hi = np.percentile(b, [1, 99])
            return (float(round(lo, 4)), float(round(max(hi, lo + 1e-4), 4)), "beta^2 (this frame)")
        return (*palette.BETA2_RANGE, "beta^2")
    return None


def visualize_output(out: dict, which: str, view: ScalarView = ScalarView()) -> np.ndarray:
    """One render output as a uint8 image: RGB as is, the scalar maps on the palette's colormap."""
    x = out.get(OUTPUT_KEY[which])
    if x is None:  # this model has no beta^2: grey
        shape = next(v for v in out.values() if v is not None).shape[:2]
        return np.full((*shape, 3), 128, np.uint8)
    if which == "RGB":
        return to_uint8(x)
    lo, hi, _ = output_range(out, which, view)
    if which == "beta^2":
        return beta2_over_render(out, lo, hi)
    return palette.colormap(np.asarray(x).reshape(x.shape[:2]), lo, hi)


def beta2_over_render(out: dict, lo: float, hi: float) -> np.ndarray:
    """beta^2 on the object, over the render: colour = (1 - opacity) rgb + opacity colormap(beta^2), so
    empty space stays as rendered and the object's own uncertainty is what stands out (uint8 RGB)."""
    b2 = np.asarray(out["beta2"], np.float32)
    colour = palette.colormap(b2.reshape(b2.shape[:2]), lo, hi).astype(np.float32)
    if out.get("opacity") is None:
        return colour.astype(np.uint8)
    o = np.clip(np.asarray(out["opacity"], np.float32).reshape(b2.shape[:2]), 0.0, 1.0)[..., None]
    rgb = to_uint8(out["rgb"]).astype(np.float32)
    return np.round((1.0 - o) * rgb + o * colour).astype(np.uint8)


def error_map(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|pred - ref| averaged over RGB on the palette's error range, uint8 RGB."""
    e = np.abs(np.asarray(pred, np.float32)[..., :3] - np.asarray(ref, np.float32)[..., :3]).mean(-1)
    return palette.colormap(e, *palette.ERROR_RANGE)


def resize_nearest(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize (H, W, ...) -> (height, width, ...)."""
    h, w = img.shape[:2]
    rows = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(int)
    cols = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(int)
    return img[rows][:, cols]


FAR_DEPTH = 100.0  # depth given to background pixels, behind every scene element


def view_depth(cam: Camera, out: dict) -> np.ndarray:
    """The renderer's ray distance -> depth along the view axis (viser composites the background image
    with it, so frustums behind the object are hidden); background pixels far. (H, W) float32."""
    d = pixel_directions(cam.width, cam.height, cam.focal)  # z = -1
    z = out["depth"].reshape(-1) / np.linalg.norm(d, axis=-1)
    z = np.where(out["opacity"].reshape(-1) > 0.5, z, FAR_DEPTH)
    return z.reshape(cam.height, cam.width).astype(np.float32)
