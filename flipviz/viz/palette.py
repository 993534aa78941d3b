"""One colour language for the browser app and the Rerun recording: the same colour for the same thing.

Things (frustums, planes) have fixed colours; scalar maps (depth, opacity, beta^2, |error|) use one
perceptual colormap on stated ranges; mirror consistency scores use red-yellow-green with fixed
thresholds.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import matplotlib
import numpy as np

RGB = tuple[int, int, int]

CAMERA: dict[str, RGB] = {
    "input": (40, 110, 230),  # blue: the observed views
    "test": (70, 70, 70),  # dark grey: the unobserved test views
    "mirror_init": (250, 190, 110),  # pale orange: mirrored cameras at their initial pose
    "mirror": (240, 120, 20),  # orange: mirrored cameras at their current, BA-refined pose
    "mirror_true": (150, 60, 200),  # purple: the exact reflections through the true plane
    "upper": (140, 90, 40),  # brown: the Upper bound's views of the unobserved side
    "novel": (220, 30, 160),  # magenta: your novel cameras
}
MIRROR_PLANE: RGB = CAMERA["mirror"]
TRUE_PLANE: RGB = CAMERA["mirror_true"]
SPHERE: RGB = (120, 160, 255)
PROBE: RGB = (0, 200, 200)  # cyan: where the pixel probe's ray meets the surface
TRAJECTORY: RGB = CAMERA["mirror"]
DROPPED: RGB = (190, 190, 190)  # pale grey: a mirrored camera the agreement gate dropped (training/flip.py)


def hex_color(rgb: RGB) -> str:
    """'#rrggbb' for web widgets (charts)."""
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def series_color(i: int, n: int) -> RGB:
    """The i-th of n distinct line colours (one per mirrored camera in a chart)."""
    r, g, b, _ = matplotlib.colormaps["turbo"](0.1 + 0.8 * i / max(1, n - 1))
    return round(255 * r), round(255 * g), round(255 * b)


SCALAR_CMAP = "viridis"  # depth, opacity, beta^2, |error|, disagreement
BETA2_RANGE = (0.0, 0.1)  # fixed, so frames compare; its floor beta_min^2 = 0.01; at the NLL optimum
# beta^2 = ||C - C_hat||^2 (Sec. IV-C), and most symmetry-breaking pixels on the chair stay below 0.1
ERROR_RANGE = (0.0, 0.5)  # |render - reference|, mean over RGB
OPACITY_RANGE = (0.0, 1.0)

SCORE_CMAP = "RdYlGn"
SCORE_RANGE = (15.0, 30.0)  # dB: red at or below 15 (the flipped view contradicts the model), green at or above 30


def colormap(x: np.ndarray, lo: float, hi: float, name: str = SCALAR_CMAP) -> np.ndarray:
    """Scalar map (H, W) -> uint8 RGB (H, W, 3) on the fixed range [lo, hi]; NaN shows as lo."""
    x = np.nan_to_num(np.asarray(x, dtype=np.float64), nan=lo, posinf=hi, neginf=lo)
    t = np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return (matplotlib.colormaps[name](t)[..., :3] * 255.0 + 0.5).astype(np.uint8)


def score_color(psnr_db: float) -> RGB:
    """A mirror consistency score (dB) on the red-yellow-green scale of SCORE_RANGE."""
    if not np.isfinite(psnr_db):
        return (160, 160, 160)
    c = colormap(np.array([psnr_db]), *SCORE_RANGE, name=SCORE_CMAP)[0]
    return int(c[0]), int(c[1]), int(c[2])


@lru_cache(maxsize=32)
def colorbar(lo: float, hi: float, label: str, name: str = SCALAR_CMAP, width: int = 320) -> np.ndarray:
    """A horizontal colour bar with its range and label, uint8 RGB (about 46 x width)."""

    bar = np.repeat(colormap(np.linspace(lo, hi, width)[None], lo, hi, name), 14, axis=0)
    canvas = np.full((46, width, 3), 255, np.uint8)
    canvas[:14] = bar
    font, scale, ink = cv2.FONT_HERSHEY_SIMPLEX, 0.42, (30, 30, 30)
    lo_s, hi_s = f"{lo:g}", f"{hi:g}"
    cv2.putText(canvas, lo_s, (2, 30), font, scale, ink, 1, cv2.LINE_AA)
    (w, _), _ = cv2.getTextSize(hi_s, font, scale, 1)
    cv2.putText(canvas, hi_s, (width - w - 2, 30), font, scale, ink, 1, cv2.LINE_AA)
    (w, _), _ = cv2.getTextSize(label, font, scale, 1)
    cv2.putText(canvas, label, ((width - w) // 2, 43), font, scale, ink, 1, cv2.LINE_AA)
    return canvas


LEGEND: tuple[tuple[tuple[RGB, ...], str], ...] = (  # (colour(s), what): every colour the 3D view draws
    ((CAMERA["input"],), "input cameras"),
    ((CAMERA["test"],), "unobserved test cameras"),
    ((CAMERA["mirror"],), "mirrored cameras (BA-refined), their trails, the mirror plane"),
    ((CAMERA["mirror_init"],), "mirrored cameras for a plane you moved (preview)"),
    ((DROPPED,), "mirrored cameras dropped for disagreeing with the inputs"),
    ((CAMERA["mirror_true"],), "exact reflections, the true symmetry plane"),
    ((CAMERA["upper"],), "Upper-bound cameras"),
    ((CAMERA["novel"],), "your novel cameras and keyframes"),
    ((SPHERE,), "the fitted camera sphere"),
    ((PROBE,), "the pixel probe's point on the surface"),
    (
        tuple(score_color(db) for db in (SCORE_RANGE[0], sum(SCORE_RANGE) / 2, SCORE_RANGE[1])),
        "mirror scores: contradicts / partly / agrees",
    ),
)


def legend_image(width: int = 360, row: int = 22) -> np.ndarray:
    """The legend as an image (uint8 RGB): a swatch of each colour, exactly as drawn, and what it marks."""
    img = np.full((row * len(LEGEND) + 4, width, 3), 255, np.uint8)
    for i, (colours, what) in enumerate(LEGEND):
        y = 2 + i * row
        for j, c in enumerate(colours):
            img[y + 4 : y + row - 4, 4 + j * 12 : 4 + (j + 1) * 12] = c
        cv2.putText(img, what, (48, y + row - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (30, 30, 30), 1, cv2.LINE_AA)
    return img
