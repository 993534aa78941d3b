"""Mirrored views and their camera poses (paper Sec. IV-A, "Initial Camera Pose").

Just Flip mirrors each input image left-right and gives it an initial pose: reflect the camera
centre through a plane through the centre of the least-squares sphere of the input centres, put it
back on the sphere, and look at the sphere centre with up = +z. `initial_mirrored_camera` does
exactly that. `exact_reflected_camera` is the ground truth for a plane-symmetric object: the whole
camera reflected through the true symmetry plane, with its x axis negated so that it stays a proper
rotation; rendering from it gives exactly the flipped image (see `flipviz.data.cameras`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from flipviz.data.cameras import WORLD_UP, Camera, View
from flipviz.data.dataset import MAX_COORDINATE, DatasetError, Plane
from flipviz.geometry.poses import look_at, pose_errors, reflection_matrix
from flipviz.geometry.sphere import Sphere, fit_camera_sphere

PRESETS: tuple[str, ...] = ("opposite", "official", "scene")


# Paper Sec. IV-A: the flipped images I' (u -> W-1-u).
def flip_image(img: np.ndarray) -> np.ndarray:
    """Horizontal flip of an (H, W, ...) image or per-pixel map: pixel u goes to W-1-u."""
    img = np.asarray(img)
    if img.ndim < 2:
        raise ValueError(f"flip_image: expected an (H, W, ...) array, got shape {img.shape}")
    return np.ascontiguousarray(img[:, ::-1])


# Paper Sec. IV-A: "symmetrical transformation through the symmetric plane".
def reflect_points(p: np.ndarray, plane: Plane) -> np.ndarray:
    """Reflect points (..., 3) through `plane`: p' = p - 2 ((p - p0) . n) n."""
    p = np.asarray(p, dtype=np.float64)
    d = (p - plane.point) @ plane.normal
    return p - 2.0 * d[..., None] * plane.normal


# Paper Sec. IV-A: the transformed centre lies on the fitted sphere.
def project_to_sphere(p: np.ndarray, sphere: Sphere) -> np.ndarray:
    """Closest point of the sphere to p (..., 3), along the ray from the sphere centre through p."""
    v = np.asarray(p, dtype=np.float64) - sphere.center
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("project_to_sphere: a point coincides with the sphere centre")
    return sphere.center + sphere.radius * v / n


def parse_plane(s: str) -> Plane:
    """Parse a user plane 'px,py,pz;nx,ny,nz' (a point on it; its normal) into a Plane."""
    usage = "expected auto, opposite, official, scene or 'px,py,pz;nx,ny,nz' (a point; a non-zero normal)"
    parts = str(s).split(";")
    if len(parts) != 2:
        raise DatasetError(f"bad mirror plane {s!r}: {usage}")
    try:
        point, normal = ([float(x) for x in part.split(",")] for part in parts)
    except ValueError:
        raise DatasetError(f"bad mirror plane {s!r}: {usage}") from None
    if len(point) != 3 or len(normal) != 3 or not np.all(np.isfinite(point + normal)):
        raise DatasetError(f"bad mirror plane {s!r}: {usage}")
    if max(map(abs, point + normal)) > MAX_COORDINATE:  # its arithmetic (reflections, offsets) would overflow
        raise DatasetError(f"bad mirror plane {s!r}: its numbers must lie within +-{MAX_COORDINATE:g}")
    if np.linalg.norm(normal) < 1e-12:
        raise DatasetError(f"bad mirror plane {s!r}: the normal is zero")
    return Plane(np.array(point), np.array(normal))


def _cameras(items: Sequence[Camera | View]) -> list[Camera]:
    return [v.camera if isinstance(v, View) else v for v in items]


# Paper Sec. IV-A: "the symmetric plane that intersects the center of the sphere".
def mirror_plane(
    preset: str,
    input_cameras: Sequence[Camera | View],
    sphere: Sphere,
    scene_plane: Plane | None = None,
    up: np.ndarray = WORLD_UP,
) -> Plane:
    """The mirror plane for a preset name or a user string 'px,py,pz;nx,ny,nz'.

    opposite: vertical (containing `up`), through the sphere centre, normal = the mean horizontal
              direction from the centre to the input cameras, so the observed side maps onto the
              unobserved one.
    official: the plane x = 0 (point (0,0,0), normal (1,0,0)), what the authors' code uses.
    scene:    the scene's true symmetry plane (error when the scene has none).
    """
    name = str(preset).strip().lower()
    if name == "opposite":
        up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        h = np.stack([c.center for c in _cameras(input_cameras)]) - sphere.center
        h -= (h @ up)[:, None] * up
        norms = np.linalg.norm(h, axis=1, keepdims=True)
        if np.any(norms < 1e-9):
            raise DatasetError("mirror plane 'opposite': a camera lies straight above/below the sphere centre")
        m = (h / norms).mean(0)
        if np.linalg.norm(m) < 1e-6:
            raise DatasetError("mirror plane 'opposite': the input cameras surround the object, no unobserved side")
        return Plane(sphere.center.copy(), m)
    if name == "official":
        return Plane(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    if name == "scene":
        if scene_plane is None:
            raise DatasetError("mirror plane 'scene': this scene has no known symmetry plane")
        return scene_plane
    if ";" not in name:
        raise DatasetError(f"unknown mirror plane {preset!r}: use auto | {' | '.join(PRESETS)} or 'px,py,pz;nx,ny,nz'")
    return parse_plane(str(preset).strip())


# Paper Sec. IV-A: reflect the centre, back onto the sphere, look at the sphere centre, up = +z.
def initial_mirrored_camera(cam: Camera, plane: Plane, sphere: Sphere, up: np.ndarray = WORLD_UP) -> Camera:
    """The paper's initial pose pi' of the flipped image of `cam` (named '<name>_flip')."""
    c = project_to_sphere(reflect_points(cam.center, plane), sphere)
    return cam.with_pose(look_at(c, sphere.center, up), name=f"{cam.name}_flip")


# Ground truth for a plane-symmetric object: R' = M R diag(-1, 1, 1), c' = reflect(c).
def exact_reflected_camera(cam: Camera, plane: Plane) -> Camera:
    """The camera whose image of a plane-symmetric object is exactly the flipped image of `cam`.

    M = I - 2 n n^T reflects the whole camera; negating its x axis (the image flip u -> W-1-u)
    makes det = +1 again. Named '<name>_flip_exact'.
    """
    c2w = np.eye(4)
    c2w[:3, :3] = reflection_matrix(plane.normal) @ cam.rotation @ np.diag([-1.0, 1.0, 1.0])
    c2w[:3, 3] = reflect_points(cam.center, plane)
    return cam.with_pose(c2w, name=f"{cam.name}_flip_exact")


def mirror_cameras_for_plane(
    inputs: Sequence[Camera | View], plane: Plane, sphere: Sphere, up: np.ndarray, pose: str
) -> list[Camera]:
    """Initial mirrored cameras ('<name>_flip') for all inputs and a plane (the app recomputes these live).

    pose "lookat": the paper's initial pose (exact only when the plane holds the sphere centre and the
    cameras look at it); "reflect": each camera reflected whole through the plane (exact for an object
    symmetric about that plane, on any trajectory).
    """
    if pose == "reflect":
        return [
            (m := exact_reflected_camera(c, plane)).with_pose(m.c2w, name=f"{c.name}_flip") for c in _cameras(inputs)
        ]
    return [initial_mirrored_camera(c, plane, sphere, up) for c in _cameras(inputs)]


def camera_sphere(inputs: Sequence[Camera | View], center: np.ndarray | None = None) -> Sphere:
    """The sphere the mirrored cameras sit on: the paper's least-squares fit through the input
    centres, or, when the object's `center` is known from the data (captures on any trajectory,
    where a sphere through a drive-by is meaningless), the sphere about it at the cameras' mean distance."""
    cams = _cameras(inputs)
    if center is None:
        return fit_camera_sphere(cams)
    center = np.asarray(center, dtype=np.float64)
    return Sphere(center, float(np.mean([np.linalg.norm(c.center - center) for c in cams])))


@dataclass
class MirrorSet:
    """The mirrored half of a Flip run: plane, sphere, flipped views with initial poses, truth."""

    plane: Plane
    sphere: Sphere
    views: list[View]  # flipped images (and alpha) with the initial mirrored cameras
    true_cameras: list[Camera] | None = None  # exact reflections through the scene's true plane
    meta: dict = field(default_factory=dict)

    @property
    def cameras(self) -> list[Camera]:
        return [v.camera for v in self.views]

    def errors_to_truth(self, cameras: Sequence[Camera] | None = None) -> list[tuple[float, float]] | None:
        """(rotation deg, translation) of `cameras` (default: the initial ones) against the truth."""
        if self.true_cameras is None:
            return None
        cams = self.cameras if cameras is None else list(cameras)
        return [pose_errors(c.c2w, t.c2w) for c, t in zip(cams, self.true_cameras, strict=True)]


def make_mirror_set(
    inputs: Sequence[View],
    plane_preset: str | Plane,
    scene_plane: Plane | None = None,
    center: np.ndarray | None = None,
    up: np.ndarray = WORLD_UP,
    *,
    pose: str,
) -> MirrorSet:
    """Paper Sec. IV-A end to end: sphere through the input centres, plane, flipped views, poses.

    `plane_preset` is a preset name, a user string, or a Plane (e.g. one estimated from the inputs);
    `center` and `up` come from the scene (captures: from the data; orbits: None and +z); `pose`
    is "lookat" or "reflect" (`mirror_cameras_for_plane`), always said: TrainConfig.mirror_pose decides.
    """
    if len(inputs) == 0:
        raise DatasetError("no input views to mirror")
    sphere = camera_sphere(inputs, center)
    plane = (
        plane_preset if isinstance(plane_preset, Plane) else mirror_plane(plane_preset, inputs, sphere, scene_plane, up)
    )
    views = []
    for v, cam in zip(inputs, mirror_cameras_for_plane(inputs, plane, sphere, up, pose)):
        alpha = None if v.alpha is None else flip_image(v.alpha)
        meta = {"mirrored": True, "source": v.name, "source_index": v.index}
        views.append(View(camera=cam, rgb=flip_image(v.rgb), alpha=alpha, index=-1, meta=meta))
    true = None if scene_plane is None else [exact_reflected_camera(v.camera, scene_plane) for v in inputs]
    preset = "estimated" if isinstance(plane_preset, Plane) else str(plane_preset)
    return MirrorSet(plane, sphere, views, true, meta={"preset": preset, "pose": pose})
