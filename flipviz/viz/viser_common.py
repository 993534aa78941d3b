"""Small helpers shared by the viser app: the one camera-convention conversion, images, scalar maps.

flipviz cameras are OpenGL (look along -z, +y up; `flipviz.data.cameras`). viser's frustums,
gizmos and viewer cameras are OpenCV (look along +z, +y down). The two differ by a flip of the
camera's y and z axes: c2w_cv = c2w_gl @ diag(1, -1, -1, 1) (and back, the matrix is its own
inverse). `to_viser_pose` / `camera_from_viser` are the only places that convert.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import viser.transforms as vtf

from flipviz.data.cameras import Camera, pixel_directions
from flipviz.data.dataset import Plane
from flipviz.data.images import to_uint8
from flipviz.viz import palette

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def to_viser_pose(c2w_gl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """flipviz (OpenGL) camera-to-world -> viser (wxyz, position) of the OpenCV camera frame."""
    T = np.asarray(c2w_gl, dtype=np.float64) @ GL_TO_CV
    return vtf.SO3.from_matrix(T[:3, :3]).wxyz, T[:3, 3].copy()


def c2w_from_viser(wxyz, position) -> np.ndarray:
    """viser (wxyz, position) of an OpenCV camera frame -> flipviz (OpenGL) camera-to-world."""
    T = np.eye(4)
    T[:3, :3] = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T @ GL_TO_CV


def camera_from_viser(wxyz, position, fov_y: float, width: int, height: int, name: str = "") -> Camera:
    """A flipviz Camera from a viser pose and a vertical field of view (radians)."""
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(c2w_from_viser(wxyz, position), int(width), int(height), float(focal), name)


def plane_wxyz(plane: Plane) -> np.ndarray:
    """Rotation whose local +z axis is the plane's normal (the plane gizmo's frame)."""
    return vtf.SO3.from_matrix(plane.basis()).wxyz


def plane_from_pose(wxyz, position) -> Plane:
    """The plane through the gizmo's position whose normal is the gizmo's local +z axis."""
    R = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    return Plane(np.asarray(position, dtype=np.float64), R[:, 2])


def plane_to_arg(plane: Plane) -> str:
    """The `--mirror-plane` string 'px,py,pz;nx,ny,nz' of a plane."""

    def fmt(v: np.ndarray) -> str:
        return ",".join(f"{round(float(x), 5) + 0.0:g}" for x in v)  # + 0.0 turns -0 into 0

    return fmt(plane.point) + ";" + fmt(plane.normal)


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
