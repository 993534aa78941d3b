"""Data layer: cameras, datasets, built-in scenes, the Blender, nerfstudio and COLMAP formats, the
protocol and protocol-free input selection."""

from __future__ import annotations

from pathlib import Path

from flipviz.data.blender import export_scene, load_blender, write_blender
from flipviz.data.builtin import load_builtin, orbit_camera, render_view
from flipviz.data.cameras import Camera, View
from flipviz.data.colmap import find_model, load_colmap
from flipviz.data.dataset import DatasetError, Plane, SceneData, TooWide
from flipviz.data.nerfstudio import load_nerfstudio, write_nerfstudio
from flipviz.data.protocol import RING_INDICES, Split, make_split, observed_positions
from flipviz.data.scenes import SCENES, build_mesh, symmetry_plane


def load_scene(scene: str, data: Path | None = None, res: int = 100) -> SceneData:
    """Built-in `scene`, or the folder `data` at width `res`, whichever format it holds: a Blender
    orbit (transforms_test.json), a nerfstudio capture (transforms.json) or a COLMAP capture."""
    if data is None:
        return load_builtin(scene, res=res)
    root = Path(data)
    if not root.exists():
        raise DatasetError(f"scene folder not found: {root}")
    if (root / "transforms_test.json").is_file():
        return load_blender(root, split="test", res=res)
    if root.name == "transforms.json" or (root / "transforms.json").is_file():
        return load_nerfstudio(root, res=res)
    if find_model(root) is not None:
        return load_colmap(root, res=res)
    raise DatasetError(
        f"{root} holds no scene flipviz reads: transforms_test.json (Blender), transforms.json (nerfstudio) "
        "or a COLMAP model (sparse/0/cameras.bin or .txt)"
    )


__all__ = [
    "Camera",
    "View",
    "DatasetError",
    "TooWide",
    "Plane",
    "SceneData",
    "SCENES",
    "build_mesh",
    "symmetry_plane",
    "load_builtin",
    "orbit_camera",
    "render_view",
    "load_blender",
    "write_blender",
    "export_scene",
    "RING_INDICES",
    "Split",
    "make_split",
    "observed_positions",
    "load_scene",
    "load_nerfstudio",
    "write_nerfstudio",
    "load_colmap",
]
