"""The paper's numbers (Lee, Kang, Yu, arXiv 2303.06335): Table III and Table II.

Table III (PSNR, SSIM, LPIPS) and Table II as printed in the paper. Values are means over the 8
configurations of each scene.
"""

from __future__ import annotations

from flipviz.training.config import METHOD_LABELS, METHODS

METHOD_ORDER: tuple[str, ...] = METHODS
__all__ = ["METHOD_LABELS", "METHOD_ORDER", "SCENE_ORDER", "TABLE2", "TABLE3"]
SCENE_ORDER: tuple[str, ...] = ("Chairs", "Lego", "Materials", "Ship", "Drum", "Ficus", "Hotdog", "Mic")


def _rows(text: str) -> dict[str, dict[str, float]]:
    out = {}
    for line in text.strip().splitlines():
        name, *vals = line.split()
        out[name] = dict(zip(METHOD_ORDER, map(float, vals), strict=True))
    return out


# Table III, columns B/L, B/L+U, Flip, Flip+U, Upper.
TABLE3: dict[str, dict[str, dict[str, float]]] = {
    "psnr": _rows("""
        Chairs    14.07 16.46 19.69 19.86 26.96
        Lego      11.57 14.85 15.24 17.79 23.91
        Materials  9.66 16.74 17.29 19.14 25.60
        Ship       6.73 16.97 18.29 18.70 24.77
        Drum      10.24 11.91 11.90 13.77 20.19
        Ficus     11.20 15.59 17.15 18.02 22.59
        Hotdog    13.67 19.07 18.91 18.92 28.30
        Mic       12.89 14.16 13.78 14.30 24.93
        Mean      11.25 15.71 16.53 17.56 24.65
    """),
    "ssim": _rows("""
        Chairs    0.75 0.78 0.87 0.88 0.92
        Lego      0.65 0.67 0.74 0.78 0.87
        Materials 0.66 0.75 0.81 0.83 0.90
        Ship      0.55 0.65 0.71 0.72 0.80
        Drum      0.60 0.59 0.63 0.68 0.83
        Ficus     0.72 0.78 0.81 0.82 0.88
        Hotdog    0.70 0.83 0.84 0.84 0.93
        Mic       0.82 0.78 0.82 0.80 0.93
        Mean      0.68 0.72 0.77 0.79 0.88
    """),
    "lpips": _rows("""
        Chairs    0.48 0.28 0.13 0.12 0.05
        Lego      0.50 0.34 0.23 0.20 0.11
        Materials 0.50 0.31 0.18 0.14 0.09
        Ship      0.61 0.40 0.27 0.26 0.18
        Drum      0.55 0.43 0.47 0.43 0.16
        Ficus     0.33 0.22 0.15 0.13 0.10
        Hotdog    0.44 0.22 0.19 0.21 0.07
        Mic       0.46 0.30 0.38 0.30 0.07
        Mean      0.48 0.30 0.25 0.22 0.10
    """),
}

# Table II (ablation of Flip+U): (bundle adjustment, uncertainty) -> scores, mean over scenes.
TABLE2: dict[tuple[bool, bool], dict[str, float]] = {
    (False, False): {"psnr": 16.636, "ssim": 0.787, "lpips": 0.232},
    (True, False): {"psnr": 17.205, "ssim": 0.789, "lpips": 0.230},
    (False, True): {"psnr": 16.694, "ssim": 0.790, "lpips": 0.240},
    (True, True): {"psnr": 17.620, "ssim": 0.794, "lpips": 0.229},
}

# NeRF-synthetic folder names (as in nerf_synthetic/) -> the paper's row name.
NERF_SYNTHETIC: dict[str, str] = {
    "chair": "Chairs",
    "chairs": "Chairs",
    "lego": "Lego",
    "materials": "Materials",
    "ship": "Ship",
    "drums": "Drum",
    "drum": "Drum",
    "ficus": "Ficus",
    "hotdog": "Hotdog",
    "mic": "Mic",
}


def paper_row(scene: str) -> str | None:
    """The paper's Table III row for a NeRF-synthetic scene folder name, else None."""
    return NERF_SYNTHETIC.get(scene.lower())
