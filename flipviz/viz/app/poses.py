"""viser's camera convention, the one conversion: flipviz cameras are OpenGL (look along -z, +y up;
`flipviz.data.cameras`); viser's frustums, gizmos and viewer cameras are OpenCV (look along +z, +y down).
The two differ by a flip of the camera's y and z axes: c2w_cv = c2w_gl @ diag(1, -1, -1, 1) (and back,
the matrix is its own inverse). `to_viser_pose` / `camera_from_viser` are the only places that convert.
"""

from __future__ import annotations

import math

import numpy as np
import viser.transforms as vtf

from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane

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
