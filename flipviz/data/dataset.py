"""The dataset type shared by built-in scenes and Blender-format folders."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flipviz.data.cameras import View


class DatasetError(ValueError):
    """Bad input data. Its message is one line, meant to be shown to the user as is."""


@dataclass(frozen=True)
class Plane:
    """A plane through `point` with unit `normal` (world coordinates)."""

    point: np.ndarray  # (3,)
    normal: np.ndarray  # (3,), unit length

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm < 1e-12:
            raise ValueError("plane normal must be a non-zero finite vector")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "point", np.asarray(self.point, dtype=np.float64).reshape(3))

    def to_dict(self) -> dict:
        return {"point": self.point.tolist(), "normal": self.normal.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Plane":
        return cls(np.asarray(d["point"]), np.asarray(d["normal"]))


@dataclass
class SceneData:
    """A scene's source orbit: views keyed by orbit index, plus what is known about the scene.

    The protocol (`flipviz.data.protocol`) picks input / test / upper views from `views` by
    orbit index, so built-in scenes and NeRF-synthetic folders are handled identically.
    """

    name: str
    views: dict[int, View]  # orbit index -> view
    near: float  # ray near bound (world units)
    far: float  # ray far bound
    bbox: np.ndarray  # (2, 3) axis-aligned box that contains the object
    symmetry_plane: Plane | None = None  # ground-truth mirror plane, when the scene has one
    source: str = ""  # "builtin:<name>" or the folder it was read from
    meta: dict = field(default_factory=dict)

    @property
    def resolution(self) -> tuple[int, int]:
        v = next(iter(self.views.values()))
        return v.camera.width, v.camera.height
