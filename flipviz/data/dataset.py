"""The dataset type shared by built-in scenes and Blender-format folders."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flipviz.data.cameras import WORLD_UP, View
from flipviz.errors import UserError

MAX_COORDINATE = 1e6  # scene units: a camera further out is a damaged file (its arithmetic would overflow)


class DatasetError(UserError):
    """Bad input data. Its message is one line, meant to be shown to the user as is."""


class TooWide(DatasetError):
    """--res asks for more pixels than the images have (flipviz does not upscale); `width`: theirs."""

    def __init__(self, res: int, width: int, where: object) -> None:
        super().__init__(f"--res {res} is wider than the images of {where} ({width} px); flipviz does not upscale")
        self.width = width


def check_width(res: int | None, width: int, where: object) -> None:
    """Images `width` px wide, asked for at --res `res` (None: their own): TooWide when they are narrower."""
    if res is not None and res > width:
        raise TooWide(res, width, where)


MAX_JSON_BYTES = 64 * 2**20  # a transforms file of 10,000 frames with their own intrinsics is about 8 MB
MAX_FRAMES = 10_000  # frames in one transforms file: more is a damaged or hostile file, not a capture


def read_transforms(path: Path) -> dict:
    """A transforms JSON file (Blender or nerfstudio) as a dict; one-line DatasetError otherwise. Its
    size (MAX_JSON_BYTES) and its frame count (MAX_FRAMES) are bounded before anything is built."""
    if path.stat().st_size > MAX_JSON_BYTES:
        mb = path.stat().st_size / 2**20
        raise DatasetError(
            f"{path} is {mb:.0f} MB; flipviz reads transforms files of at most {MAX_JSON_BYTES >> 20} MB"
        )
    try:
        meta = json.loads(path.read_text(), parse_constant=_not_json)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path} is not valid JSON ({str(e).splitlines()[0]})") from None
    except RecursionError:
        raise DatasetError(f"{path} is malformed: its JSON nests too deeply") from None
    if not isinstance(meta, dict):
        raise DatasetError(
            f"{path} is malformed: the top level is a JSON {type(meta).__name__}, not an object with 'frames'"
        )
    frames = meta.get("frames")
    if isinstance(frames, list) and len(frames) > MAX_FRAMES:
        raise DatasetError(f"{path} lists {len(frames):,} frames; flipviz reads at most {MAX_FRAMES:,}")
    return meta


def _not_json(name: str) -> float:
    """NaN and Infinity are not JSON (Python's reader accepts them): refuse them in any field."""
    raise json.JSONDecodeError(f"{name} is not a JSON number", name, 0)


def check_resolution(res: object) -> None:
    """--res for a data folder: None (the data's own) or a positive integer."""
    if res is not None and (isinstance(res, bool) or not isinstance(res, (int, np.integer)) or res < 1):
        raise DatasetError(f"resolution must be a positive integer, got {res!r}")


MIN_SIDE = 8  # px: an image smaller on a side has no structure to score (SSIM's window is 7 px)


def check_image_size(width: int, height: int, what: str) -> None:
    """Images (as loaded, after any resize) a run can score: at least MIN_SIDE px on each side; else one line."""
    if min(width, height) < MIN_SIDE:
        raise DatasetError(f"{what}: {width}x{height} px; a run needs at least {MIN_SIDE} px on each side")


def camera_to_world(matrix: object, k: int) -> np.ndarray:
    """Frame k's transform_matrix (4x4, or 3x4) as a checked c2w; ValueError naming the frame."""
    c2w = np.asarray(matrix, dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]])
    if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
        raise ValueError(f"frame {k}: transform_matrix is not a finite 4x4 matrix")
    if np.abs(c2w[:3, 3]).max() > MAX_COORDINATE:
        raise ValueError(
            f"frame {k}: the camera is {np.abs(c2w[:3, 3]).max():.3g} units out, beyond {MAX_COORDINATE:g}"
        )
    R = c2w[:3, :3]
    with np.errstate(all="ignore"):  # huge entries overflow here: the check below refuses them
        orthonormal = np.allclose(R.T @ R, np.eye(3), atol=1e-3) and abs(np.linalg.det(R) - 1.0) <= 1e-3
    if not orthonormal:
        raise ValueError(f"frame {k}: the rotation of transform_matrix is not a rotation (orthonormal, det 1)")
    return c2w


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
        p = np.asarray(self.point, dtype=np.float64).reshape(3)
        if not np.all(np.abs(p) <= MAX_COORDINATE):  # NaN too
            raise ValueError(f"plane point must be finite and within +-{MAX_COORDINATE:g}")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "point", p)

    def to_dict(self) -> dict:
        return {"point": self.point.tolist(), "normal": self.normal.tolist()}

    def basis(self) -> np.ndarray:
        """Rotation (3, 3) whose columns u, v, n span the plane (u, v) and give its normal (n)."""
        n = self.normal
        helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(helper, n)
        u /= np.linalg.norm(u)
        return np.stack([u, np.cross(n, u), n], axis=1)

    def square(self, half: float) -> np.ndarray:
        """The 4 corners (4, 3) of a square of half-size `half` in the plane, centred on its point."""
        u, v = self.basis()[:, 0], self.basis()[:, 1]
        return np.stack([self.point + half * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])

    @classmethod
    def from_dict(cls, d: dict) -> Plane:
        return cls(np.asarray(d["point"]), np.asarray(d["normal"]))


@dataclass
class SceneData:
    """A scene's views keyed by index, plus what is known about the scene.

    Orbit data (built-in scenes, NeRF-synthetic folders; `protocol` True): the index is the orbit
    index and the protocol (`flipviz.data.protocol`) picks input / test / Upper views from it.
    Captures (nerfstudio, COLMAP; `protocol` False): the index is the frame number; `splits` names
    the capture's own train / test frames, and `data/selection.py` picks the inputs.
    """

    name: str
    views: dict[int, View]  # orbit index -> view
    near: float  # ray near bound (world units)
    far: float  # ray far bound
    bbox: np.ndarray  # (2, 3) axis-aligned box that contains the object
    symmetry_plane: Plane | None = None  # ground-truth mirror plane, when the scene has one
    source: str = ""  # "builtin:<name>" or the folder it was read from
    meta: dict = field(default_factory=dict)
    protocol: bool = True  # views follow the protocol's orbit indices
    splits: dict[str, list[int]] = field(default_factory=dict)  # a capture's named frame lists ("train", "test")
    up: np.ndarray = field(default_factory=lambda: WORLD_UP.copy())  # world up (captures: estimated from the cameras)
    up_known: bool = True  # False when `up` is only an estimate
    center: np.ndarray | None = (
        None  # the object's centre, look-at target of the mirrors (None: the paper's sphere fit)
    )

    @property
    def resolution(self) -> tuple[int, int]:
        v = next(iter(self.views.values()))
        return v.camera.width, v.camera.height
