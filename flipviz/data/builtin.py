"""Built-in scenes as `SceneData` on the protocol's orbit, with an on-disk render cache.

Orbit (the protocol's built-in scenes): index i sits at azimuth i * 3.6 degrees, counted
counter-clockwise (seen from +z) from the +y axis as on the NeRF-synthetic test orbit (whose index
0 looks from +y), at a fixed elevation of 30 degrees and radius 4, looking at the origin with up
+z. Focal length from lego's camera_angle_x. Only the views the protocol needs are rendered by
default: the 16 ring views and the 16 Upper views (ring index + 1).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from flipviz.data.cameras import Camera, View, look_at
from flipviz.data.dataset import DatasetError, SceneData
from flipviz.data.protocol import protocol_indices
from flipviz.data.raycast import render_depth, render_mesh
from flipviz.data.scenes import cached_mesh, symmetry_plane
from flipviz.files import atomic_path

RENDERER_VERSION = 1  # bump whenever geometry, colours, shading or the orbit change
CAMERA_ANGLE_X = 0.6911112070083618  # NeRF-synthetic lego
DEG_PER_INDEX = 3.6
ELEVATION_DEG = 30.0
RADIUS = 4.0
NEAR, FAR = 2.0, 6.0


def focal_px(res: int) -> float:
    """The built-in cameras' focal length in pixels at width `res` (lego's field of view)."""
    return float(0.5 * res / np.tan(0.5 * CAMERA_ANGLE_X))


def ring_camera(azimuth_deg: float, res: int, name: str) -> Camera:
    """A res x res camera on the orbit's ring (RADIUS, ELEVATION_DEG) at `azimuth_deg` (about +z,
    from +x), looking at the origin."""
    az, el = np.radians(azimuth_deg), np.radians(ELEVATION_DEG)
    center = RADIUS * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Camera(look_at(center, np.zeros(3)), res, res, focal_px(res), name=name)


def orbit_camera(index: int, res: int = 100) -> Camera:
    """The built-in orbit's camera number `index` at resolution res x res."""
    return ring_camera(90.0 + DEG_PER_INDEX * index, res, f"r_{index}")  # index 0 on +y, as on the NeRF-synthetic orbit


_warm_lock = threading.Lock()
_warm: set[str] = set()


def _scene_mesh(name: str):
    """The cached mesh with its lazily built caches (BVH, normals, colours) built once, under a lock,
    so that concurrent renders (trainer thread, app thread) are safe."""
    mesh = cached_mesh(name)
    if name not in _warm:
        with _warm_lock:
            if name not in _warm:
                mesh.face_normals, mesh.visual.face_colors  # noqa: B018
                mesh.ray.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
                _warm.add(name)
    return mesh


def render_view(name: str, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Render built-in scene `name` from any camera -> (rgb on white, alpha); the mesh is cached."""
    return render_mesh(_scene_mesh(name), camera)


def builtin_name(scene: SceneData) -> str | None:
    """The built-in scene a SceneData was made from (None for data read from a folder)."""
    return scene.source.removeprefix("builtin:") if scene.source.startswith("builtin:") else None


def true_depth(scene: SceneData, camera: Camera) -> np.ndarray | None:
    """The true depth of a built-in scene from `camera` (ray distance, inf off the object); None for data."""
    name = builtin_name(scene)
    return render_depth(_scene_mesh(name), camera) if name is not None else None


def cache_dir() -> Path:
    """Render cache folder: $FLIPVIZ_CACHE, else the per-user cache dir of flipviz."""
    env = os.environ.get("FLIPVIZ_CACHE")
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("flipviz"))


def _cache_path(name: str, res: int) -> Path:
    return cache_dir() / f"builtin-{name}-{res}px-v{RENDERER_VERSION}.npz"


def _read_cache(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    try:
        with np.load(path) as z:
            idx, rgb, alpha = z["indices"], z["rgb"], z["alpha"]  # each z[key] decompresses: read once
        return {int(i): (rgb[k], alpha[k]) for k, i in enumerate(idx)}
    except (OSError, KeyError, ValueError, EOFError):  # missing or corrupt: re-render
        return {}


def _write_cache(path: Path, renders: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
    idx = sorted(renders)
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp,
            indices=np.array(idx, dtype=np.int64),
            rgb=np.stack([renders[i][0] for i in idx]),
            alpha=np.stack([renders[i][1] for i in idx]),
        )


def load_builtin(name: str, res: int = 100, cache: bool = True, indices: Iterable[int] | None = None) -> SceneData:
    """Built-in scene `name` on the orbit at res x res: by default the protocol's 32 views."""
    plane = symmetry_plane(name)  # raises DatasetError for an unknown name
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)) or res < 4:
        raise DatasetError(f"resolution must be a positive integer, got {res!r}")
    res = int(res)
    wanted = sorted(set(protocol_indices() if indices is None else (int(i) for i in indices)))
    path = _cache_path(name, res)
    renders = _read_cache(path) if cache else {}
    todo = [i for i in wanted if i not in renders]
    for i in todo:
        renders[i] = render_view(name, orbit_camera(i, res))
    if cache and todo:
        _write_cache(path, renders)

    views = {i: View(orbit_camera(i, res), renders[i][0], renders[i][1], index=i) for i in wanted}
    bounds = np.asarray(cached_mesh(name).bounds, dtype=np.float64)
    pad = 0.05 * (bounds[1] - bounds[0]).max()
    return SceneData(
        name=name,
        views=views,
        near=NEAR,
        far=FAR,
        bbox=np.stack([bounds[0] - pad, bounds[1] + pad]),
        symmetry_plane=plane,
        source=f"builtin:{name}",
        meta={
            "orbit": f"azimuth {DEG_PER_INDEX} deg/index from +y, elevation {ELEVATION_DEG} deg, radius {RADIUS}",
            "renderer_version": RENDERER_VERSION,
        },
    )
