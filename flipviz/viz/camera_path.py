"""Camera paths for videos: round the object, across the unobserved side, or through keyframes.

    orbit_path(setup, n)            n cameras all round, at the inputs' mean distance and height
    unobserved_path(setup, n)       through the held-out test views in azimuth order (a frame lands
                                    on each test view, so its ground truth is shown there)
    keyframe_path(setup, keys, n)   through cameras recorded in the app (keyframes.json) or
                                    nerfstudio's camera_path.json
`setup` is the run's SetupEvent (its cameras, centre and up).

Between two keyframes the position moves on the sphere about the run's centre (azimuth, elevation
and distance interpolated linearly) and the rotation by slerp, so an orbit stays an orbit and a
keyframe is hit exactly.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flipviz.data.cameras import Camera, azimuth_deg, horizontal_basis, look_at
from flipviz.errors import UserError
from flipviz.files import write_json

KEYFRAMES_FILE = "keyframes.json"


def _spherical(p: np.ndarray, center: np.ndarray, up: np.ndarray) -> tuple[float, float, float]:
    """(azimuth deg, elevation deg, distance) of point p about `center`, azimuth as in `azimuth_deg`."""
    d = p - center
    r = float(np.linalg.norm(d))
    el = float(np.degrees(np.arcsin(np.clip(d @ up / max(r, 1e-12), -1.0, 1.0))))
    return azimuth_deg(d, up), el, r


def _point(az: float, el: float, r: float, center: np.ndarray, up: np.ndarray) -> np.ndarray:
    u, v = horizontal_basis(up)
    a, e = np.radians(az), np.radians(el)
    return center + r * (np.cos(e) * (np.cos(a) * u + np.sin(a) * v) + np.sin(e) * up)


def interpolate(keys: list[Camera], n: int, center: np.ndarray, up: np.ndarray) -> list[Camera]:
    """n cameras through `keys` in order, evenly spread in keyframe time; keys[0] and keys[-1] included."""
    if len(keys) < 2 or n <= len(keys):
        return [c.with_pose(c.c2w, name=f"frame_{i:04d}") for i, c in enumerate(keys[: max(n, 1)])]
    sph = np.array([_spherical(c.center, center, up) for c in keys])
    sph[:, 0] = np.degrees(np.unwrap(np.radians(sph[:, 0])))  # the short way between neighbours
    knots = np.arange(len(keys), dtype=np.float64)
    slerp = Slerp(knots, Rotation.from_matrix(np.stack([c.rotation for c in keys])))
    ts = np.linspace(0.0, len(keys) - 1, n)
    rots = slerp(ts).as_matrix()
    out = []
    for i, t in enumerate(ts):
        k = min(int(t), len(keys) - 2)
        f = t - k
        az, el, r = (1 - f) * sph[k] + f * sph[k + 1]
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rots[i], _point(az, el, r, center, up)
        ref = keys[k] if f < 0.5 else keys[k + 1]
        out.append(ref.with_pose(c2w, name=f"frame_{i:04d}"))
    return out


def _ring(setup, n: int, az0: float, span: float) -> list[Camera]:
    """n cameras on an arc from azimuth az0 over `span` degrees, at the inputs' mean height and
    distance from the run's centre, each looking at the centre."""
    center, up = np.asarray(setup.sphere_center), np.asarray(setup.up)
    inputs = [c.camera for c in setup.cameras if c.kind == "input"]
    sph = np.array([_spherical(c.center, center, up) for c in inputs])
    el, r = float(sph[:, 1].mean()), float(sph[:, 2].mean())
    template = inputs[0]
    cams = []
    for i in range(n):
        az = az0 + span * i / (n if span >= 360.0 else max(n - 1, 1))
        cams.append(template.with_pose(look_at(_point(az, el, r, center, up), center, up), name=f"frame_{i:04d}"))
    return cams


def input_azimuth(setup) -> float:
    """The mean azimuth (degrees) of the input cameras about the run's centre: the observed side."""
    center, up = np.asarray(setup.sphere_center), np.asarray(setup.up)
    az = np.radians([_spherical(c.camera.center, center, up)[0] for c in setup.cameras if c.kind == "input"])
    return float(np.degrees(np.arctan2(np.sin(az).mean(), np.cos(az).mean())))


def orbit_path(setup, n: int) -> list[Camera]:
    """All round the object, starting on the observed side."""
    return _ring(setup, n, input_azimuth(setup), 360.0)


def unobserved_path(setup, n: int) -> list[Camera]:
    """Across the unobserved side: through the test views sorted by azimuth (measured from the far
    side, so the arc never wraps), with frames in between."""
    tests = [c.camera for c in setup.cameras if c.kind == "test"]
    if not tests:  # nothing held out: the half ring opposite the inputs
        return _ring(setup, n, input_azimuth(setup) + 90.0, 180.0)
    center, up = np.asarray(setup.sphere_center), np.asarray(setup.up)
    far = input_azimuth(setup) + 180.0
    rel = [((_spherical(c.center, center, up)[0] - far + 180.0) % 360.0) - 180.0 for c in tests]
    keys = [tests[i] for i in np.argsort(rel)]
    if len(keys) == 1:
        return [keys[0]]
    per_gap = max(0, round((n - len(keys)) / (len(keys) - 1)))  # frames between two test views
    return interpolate(keys, (len(keys) - 1) * (per_gap + 1) + 1, center, up)


# ---- keyframes on disk --------------------------------------------------------------------------
def write_keyframes(path: Path | str, cameras: list[Camera], fps: int = 24) -> Path:
    """The app's recorded camera path: poses (OpenGL c2w), vertical field of view and aspect."""
    keys = [
        {"c2w": c.c2w.tolist(), "fov_y_deg": float(np.degrees(c.fov_y)), "aspect": c.width / c.height} for c in cameras
    ]
    return write_json(path, {"format": "flipviz-keyframes", "fps": fps, "keyframes": keys})


def read_keyframes(path: Path | str, width: int) -> list[Camera]:
    """Cameras of a keyframes.json (flipviz) or camera_path.json (nerfstudio: camera_to_world, fov in
    degrees, vertical) at `width` pixels; a malformed file is one UserError line."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        entries = data["keyframes"] if "keyframes" in data else data["camera_path"]
        cams = []
        for i, e in enumerate(entries):
            c2w = np.asarray(e["c2w"] if "c2w" in e else e["camera_to_world"], dtype=np.float64).reshape(-1)
            c2w = c2w.reshape(4, 4) if c2w.size == 16 else np.concatenate([c2w.reshape(3, 4), [[0, 0, 0, 1]]])
            fov = float(e.get("fov_y_deg", e.get("fov", 50.0)))
            aspect = float(e.get("aspect", 1.0))
            height = max(8, round(width / aspect))
            if not (0.5 < fov < 179.0 and np.isfinite(c2w).all()):
                raise ValueError(f"keyframe {i}: field of view {fov} or pose not valid")
            cams.append(Camera(c2w, width, height, 0.5 * height / np.tan(np.radians(fov) / 2), name=f"key_{i:03d}"))
    except FileNotFoundError:
        raise UserError(f"keyframes file not found: {path}") from None
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as e:
        raise UserError(f"{path} is not a keyframes file ({type(e).__name__}: {e})".splitlines()[0]) from None
    if len(cams) < 2:
        raise UserError(f"{path} holds {len(cams)} keyframe(s); a path needs at least 2")
    return cams


def keyframe_path(setup, keys: list[Camera], n: int) -> list[Camera]:
    return interpolate(keys, n, np.asarray(setup.sphere_center), np.asarray(setup.up))
