"""Geometry layer: the least-squares camera sphere, poses, and the mirrored views (paper Sec. IV-A)."""

from flipviz.geometry.mirror import (
    PRESETS,
    MirrorSet,
    exact_reflected_camera,
    flip_image,
    initial_mirrored_camera,
    make_mirror_set,
    mirror_cameras_for_plane,
    mirror_plane,
    parse_plane,
    project_to_sphere,
    reflect_points,
)
from flipviz.geometry.poses import is_proper_rotation, look_at, pose_errors, reflection_matrix, rotation_angle_deg
from flipviz.geometry.sphere import Sphere, axes_intersection, fit_camera_sphere, fit_sphere, view_direction

__all__ = [
    "PRESETS",
    "MirrorSet",
    "Sphere",
    "axes_intersection",
    "exact_reflected_camera",
    "fit_camera_sphere",
    "fit_sphere",
    "flip_image",
    "initial_mirrored_camera",
    "is_proper_rotation",
    "look_at",
    "make_mirror_set",
    "mirror_cameras_for_plane",
    "mirror_plane",
    "parse_plane",
    "pose_errors",
    "project_to_sphere",
    "reflect_points",
    "reflection_matrix",
    "rotation_angle_deg",
    "view_direction",
]
