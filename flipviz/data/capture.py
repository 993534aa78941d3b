"""What every capture loader (nerfstudio, COLMAP) shares: its cameras made flipviz cameras, its
masks, and the scene box, near/far, up and object centre taken from the data.

Cameras. flipviz's camera is an ideal pinhole with square pixels and the principal point at the
image centre (data/cameras.py): only then is a left-right flip the image of a mirrored camera. A
capture's camera (fx != fy, an off-centre principal point, OpenCV lens distortion) is resampled
once, at load time, into that camera with OpenCV (`initUndistortRectifyMap` + `remap`): same pose,
same size, focal max(fx, fy), principal point centred. Pixels the source image does not cover
become background (alpha 0).

Masks. With a mask (an RGBA image or a mask file) the object is composited on white, as for the
built-in scenes. Without one, the background is part of every image, and a flipped background is
not what a mirrored camera would see: training still uses the whole input images, but the mirrored
images keep only the rays that cross the scene box (`training/flip.rays_through_box`), and loading
says so in one line.

Scene box, from the capture's training frames (held-out frames never shape it), in order of
preference: the visual hull of the masks; the capture's sparse points
(1st-99th percentile); a nerfstudio `aabb_scale` cube; a cube around the point the cameras look at.
The object centre (the mirrors' look-at target) is the box's centre; near/far enclose the box from
every camera; `up` is the direction orthogonal to the cameras' x axes (`cameras_up`; an estimate,
`up_known` False).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flipviz.data.cameras import Camera, View, looked_at_point
from flipviz.data.dataset import DatasetError, SceneData, check_width
from flipviz.data.images import composite_on_white, image_size, read_rgba

log = logging.getLogger("flipviz.data")

HULL_RES = 48  # visual-hull voxels along each side
BOX_PAD = 0.08  # scene box padding, fraction of its largest side
NO_MASK_NOTE = (
    "no masks: the background is part of the images and a flipped background is wrong, so mirrored "
    "images keep only rays through the scene box; give masks (RGBA or mask_path) for an object-only run"
)


@dataclass(frozen=True)
class Intrinsics:
    """A capture's camera: focal lengths and principal point in pixels, OpenCV distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()  # OpenCV (k1, k2, p1, p2[, k3[, k4, k5, k6]]); () = none

    def check(self, where: str) -> Intrinsics:
        """Sizes up to 65536 px, focal lengths in (0, 1e6] px, the principal point within ten image
        sizes of the centre, |distortion| <= 1000: anything beyond is a damaged file, not a camera."""
        w, h, vals = self.width, self.height, [self.fx, self.fy, self.cx, self.cy, *self.dist]
        if not (
            0 < w <= 65536
            and 0 < h <= 65536
            and np.all(np.isfinite(vals))
            and 0 < self.fx <= 1e6
            and 0 < self.fy <= 1e6
            and abs(self.cx - w / 2) <= 10 * w
            and abs(self.cy - h / 2) <= 10 * h
            and all(abs(d) <= 1e3 for d in self.dist)
        ):
            raise DatasetError(
                f"{where}: bad intrinsics (w {w}, h {h}, fx {self.fx}, fy {self.fy}, cx {self.cx}, cy {self.cy})"
            )
        if len(self.dist) not in (0, 4, 5, 8):
            raise DatasetError(f"{where}: {len(self.dist)} distortion coefficients; OpenCV takes 4, 5 or 8")
        return self

    @property
    def is_ideal(self) -> bool:
        """Already the flipviz camera: square pixels, centred principal point, no distortion."""
        return (
            self.fx == self.fy
            and abs(self.cx - self.width / 2) < 1e-6
            and abs(self.cy - self.height / 2) < 1e-6
            and not any(self.dist)
        )


def to_pinhole(rgba: np.ndarray, intr: Intrinsics, width: int | None) -> tuple[np.ndarray, np.ndarray, float]:
    """Resample an RGBA image (H, W, 4) into the flipviz pinhole, composite on white, resize to `width`.

    Returns rgb (h, w, 3) on white, alpha (h, w) and the focal length in pixels at width w.
    """
    H, W = rgba.shape[:2]
    if (W, H) != (intr.width, intr.height):
        # intrinsics written for another resolution (e.g. downscaled images): scale them
        sx, sy = W / intr.width, H / intr.height
        intr = Intrinsics(W, H, intr.fx * sx, intr.fy * sy, intr.cx * sx, intr.cy * sy, intr.dist)
    focal = max(intr.fx, intr.fy)
    if not intr.is_ideal:
        K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]])
        K_new = np.array([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1]])
        dist = np.asarray(intr.dist, dtype=np.float64) if intr.dist else None
        # OpenCV's pixel centres are integers, flipviz's are at +0.5: the same centred K_new for both
        K_cv, K_new_cv = K.copy(), K_new.copy()
        K_cv[:2, 2] -= 0.5
        K_new_cv[:2, 2] -= 0.5
        mx, my = cv2.initUndistortRectifyMap(K_cv, dist, None, K_new_cv, (W, H), cv2.CV_32FC1)
        rgba = cv2.remap(rgba, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    rgb, alpha = composite_on_white(rgba, width)
    return rgb, alpha, focal * rgb.shape[1] / W


def read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A mask file (any image; object where > 0.5 of its first channel) -> float32 (H, W) in [0, 1]."""
    image_size(path, "mask")  # refused from its header when it is too large to decode
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise DatasetError(f"cannot read mask {path}")
    if m.ndim == 3:
        m = m[..., 0]
    m = m.astype(np.float32) / (float(np.iinfo(m.dtype).max) if np.issubdtype(m.dtype, np.integer) else 1.0)
    if m.shape != shape:
        raise DatasetError(f"mask {path} is {m.shape[1]}x{m.shape[0]}, its image {shape[1]}x{shape[0]}")
    return m


def capture_view(
    ipath: Path, mask: Path | None, intr: Intrinsics, c2w: np.ndarray, res: int | None, index: int, listed_in: str
) -> View:
    """One frame of a capture: its image (alpha from `mask`, else the image's own) resampled into the
    flipviz pinhole at width `res`; alpha None when the frame has no mask."""
    if not os.path.isfile(ipath):  # False, not an error, for a name the system refuses (too long)
        raise DatasetError(f"image {ipath} listed in {listed_in} not found")
    rgba = read_rgba(ipath)
    if mask is not None:
        rgba[..., 3] = read_mask(mask, rgba.shape[:2])
    masked = mask is not None or bool((rgba[..., 3] < 1).any())
    check_width(res, rgba.shape[1], ipath.parent)
    rgb, alpha, focal = to_pinhole(rgba, intr, res)
    return View(
        Camera(c2w, rgb.shape[1], rgb.shape[0], focal, name=ipath.stem), rgb, alpha if masked else None, index=index
    )


def hull_box(views: list[View], res: int = HULL_RES) -> np.ndarray | None:
    """Box (2, 3) of the masks' visual hull: voxels inside every silhouette that sees them (>= 2 views)."""
    cams = [v.camera for v in views]
    target = looked_at_point(cams)
    if target is None:
        return None
    dist = np.array([np.linalg.norm(c.center - target) for c in cams])
    half = float(np.median(dist) * np.tan(0.5 * max(c.fov_x for c in cams)) * 1.5)
    g = np.linspace(-half, half, res)
    pts = target + np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    inside = np.ones(len(pts), bool)
    seen = np.zeros(len(pts), np.int64)
    for v in views:
        r, u, vis = v.camera.project(pts)
        m = np.zeros(len(pts), bool)
        m[vis] = v.alpha[r[vis], u[vis]] > 0.5
        inside &= m | ~vis
        seen += vis
    keep = pts[inside & (seen >= 2)]
    if len(keep) == 0:
        return None
    step = g[1] - g[0]
    return np.stack([keep.min(0) - step, keep.max(0) + step])


def points_box(points: np.ndarray) -> np.ndarray | None:
    """Box (2, 3) of sparse points, robust to outliers: their 1st to 99th percentiles."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if len(p) < 8:
        return None
    return np.stack([np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)])


def padded(box: np.ndarray, pad: float = BOX_PAD) -> np.ndarray:
    margin = pad * float((box[1] - box[0]).max())
    return np.stack([box[0] - margin, box[1] + margin])


def near_far(cameras: list[Camera], box: np.ndarray) -> tuple[float, float]:
    """Ray bounds that enclose `box` from every camera: nearest box point and farthest corner."""
    corners = np.stack(np.meshgrid(*box.T, indexing="ij"), -1).reshape(-1, 3)
    c = np.stack([cam.center for cam in cameras])
    nearest = np.linalg.norm(c - np.clip(c, box[0], box[1]), axis=1)
    farthest = np.linalg.norm(c[:, None] - corners[None], axis=2).max(1)
    far = 1.05 * float(farthest.max())
    return max(0.9 * float(nearest.min()), 0.01 * far), far


def cameras_up(cameras: list[Camera]) -> np.ndarray:
    """World up as the cameras suggest: people and robots keep cameras level, so every camera's x
    axis is horizontal and up is the direction most orthogonal to all of them (the least singular
    vector of their stack), signed like the cameras' up axes. When the x axes are all parallel
    (no turn along the path) that direction is not determined: the mean camera up axis instead."""
    x = np.stack([c.c2w[:3, 0] for c in cameras])
    y = np.stack([c.c2w[:3, 1] for c in cameras]).mean(0)
    _, s, Vt = np.linalg.svd(x, full_matrices=False)
    up = Vt[2] if s[1] > 0.2 * s[0] else y
    up = up / np.linalg.norm(up)
    return up if up @ y >= 0 else -up


def make_capture(
    name: str,
    views: dict[int, View],
    source: str,
    splits: dict[str, list[int]],
    points: np.ndarray | None = None,
    aabb_scale: float | None = None,
    meta: dict | None = None,
) -> SceneData:
    """A capture's SceneData: scene box, near/far, centre and up from the data (module docstring)."""
    if not views:
        raise DatasetError(f"{source}: no frames")
    vs = list(views.values())
    sizes = {v.rgb.shape[:2] for v in vs}
    if len(sizes) > 1:
        raise DatasetError(f"{source}: images have different sizes {sorted(sizes)}; flipviz needs one size")
    masked = all(v.alpha is not None for v in vs)
    placing = [views[i] for i in splits.get("train", sorted(views))]  # the held-out frames never shape the box
    if not placing:
        raise DatasetError(f"{source}: no training frames (train_filenames is empty)")
    box, box_from = None, ""
    if masked:
        box, box_from = hull_box(placing), "masks"
    if box is None and points is not None:
        box, box_from = points_box(points), "sparse points"
    if box is None and aabb_scale is not None:
        box, box_from = np.array([[-1.0] * 3, [1.0] * 3]) * float(aabb_scale), "aabb_scale"
    if box is None:
        target = looked_at_point([v.camera for v in placing])
        if target is None:
            raise DatasetError(
                f"{source}: cannot place the scene: no masks, no points and the cameras look in parallel"
            )
        half = 0.5 * float(np.median([np.linalg.norm(v.camera.center - target) for v in placing]))
        box, box_from = np.stack([target - half, target + half]), "cameras"
    box = padded(box)
    near, far = near_far([v.camera for v in vs], box)
    if not masked:
        log.warning("%s: %s", source, NO_MASK_NOTE)
    return SceneData(
        name=name,
        views=views,
        near=near,
        far=far,
        bbox=box,
        symmetry_plane=None,
        source=source,
        meta={**(meta or {}), "box_from": box_from, "masked": masked},
        protocol=False,
        splits=splits,
        up=cameras_up([v.camera for v in placing]),
        up_known=False,
        center=box.mean(0),
    )
