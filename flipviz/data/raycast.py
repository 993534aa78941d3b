"""Lambert + ambient ray-cast renderer of a face-coloured mesh, from any flipviz `Camera`.

Uses trimesh's ray intersector (Embree through embreex when installed, else trimesh's pure
numpy/rtree one). Anti-aliasing: s x s supersampling whose sample pattern is symmetric about each
pixel centre (the pixel centres of the same camera at s times the resolution), so a horizontally
flipped camera samples exactly the flipped pattern and mirror identities stay exact.
"""

from __future__ import annotations

import numpy as np
import trimesh

from flipviz.data.cameras import Camera

LIGHT_DIR = np.array([0.55, 0.35, 0.76])  # direction TOWARDS the light (world), from one side on purpose
AMBIENT = 0.35


def render_mesh(
    mesh: trimesh.Trimesh,
    camera: Camera,
    light_dir: np.ndarray = LIGHT_DIR,
    ambient: float = AMBIENT,
    supersample: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Render `mesh` -> (rgb (H, W, 3) float32 composited on white, alpha (H, W) float32 in [0, 1]).

    Shading: c = albedo * (ambient + (1 - ambient) * max(0, n . l)), two-sided normals.
    """
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    W, H = camera.width, camera.height
    hi = camera.resized(W * s, H * s)  # pixel centres at u + (k + 0.5) / s: symmetric about u + 0.5
    origins, dirs = hi.rays()
    tri = mesh.ray.intersects_first(origins.astype(np.float64), dirs.astype(np.float64))
    hit = tri >= 0

    light = np.asarray(light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    n = np.asarray(mesh.face_normals)[tri[hit]]
    n = np.where((np.sum(n * dirs[hit], axis=1) > 0)[:, None], -n, n)  # face the camera
    shade = ambient + (1.0 - ambient) * np.clip(n @ light, 0.0, None)
    albedo = np.asarray(mesh.visual.face_colors)[tri[hit], :3].astype(np.float64) / 255.0

    rgb = np.ones((H * s * W * s, 3))  # white background
    rgb[hit] = albedo * shade[:, None]
    alpha = hit.astype(np.float64)
    # box-filter the s x s samples of each pixel
    rgb = rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3))
    alpha = alpha.reshape(H, s, W, s).mean(axis=(1, 3))
    return rgb.astype(np.float32), alpha.astype(np.float32)


def render_depth(mesh: trimesh.Trimesh, camera: Camera) -> np.ndarray:
    """Distance along each pixel-centre ray to the first surface hit, (H, W) float32; inf where none
    (the renderer's `depth` is the same distance, along unit rays)."""
    origins, dirs = camera.rays()
    loc, ray, _ = mesh.ray.intersects_location(origins.astype(np.float64), dirs.astype(np.float64), multiple_hits=False)
    depth = np.full(len(origins), np.inf)
    depth[ray] = np.linalg.norm(loc - origins[ray], axis=1)
    return depth.reshape(camera.height, camera.width).astype(np.float32)
