"""Data layer: cameras, datasets, built-in scenes, the Blender format and the protocol."""

from __future__ import annotations

from pathlib import Path

from flipviz.data.blender import export_scene, load_blender, write_blender
from flipviz.data.builtin import load_builtin, orbit_camera, render_view
from flipviz.data.cameras import Camera, View
from flipviz.data.dataset import DatasetError, Plane, SceneData
from flipviz.data.protocol import RING_INDICES, Split, make_split, observed_positions
from flipviz.data.scenes import SCENES, build_mesh, symmetry_plane


def load_scene(scene: str, data: Path | None = None, res: int = 100) -> SceneData:
    """A Blender-format folder when `data` is given (its test orbit at width `res`), else built-in `scene`."""
    if data is not None:
        return load_blender(data, split="test", res=res)
    return load_builtin(scene, res=res)


__all__ = [
    "Camera", "View", "DatasetError", "Plane", "SceneData", "SCENES", "build_mesh", "symmetry_plane",
    "load_builtin", "orbit_camera", "render_view", "load_blender", "write_blender", "export_scene",
    "RING_INDICES", "Split", "make_split", "observed_positions", "load_scene",
]
