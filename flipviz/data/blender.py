"""Read and write the Blender / NeRF-synthetic format: transforms_{split}.json + RGBA PNGs.

transforms_{split}.json holds `camera_angle_x` (horizontal field of view, radians) and `frames`,
each with `file_path` (relative to the folder, usually without extension) and `transform_matrix`
(4x4 OpenGL camera-to-world, the flipviz convention itself). The orbit index of a frame is its
position in `frames`, unless every frame carries an `orbit_index` (written by `write_blender`
when the views are not the contiguous orbit 0..N-1).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from flipviz.data.cameras import Camera, View
from flipviz.data.dataset import (
    DatasetError,
    SceneData,
    camera_to_world,
    check_resolution,
    check_width,
    read_transforms,
)
from flipviz.data.images import composite_on_white, read_rgba, save_rgba_png, uncomposite
from flipviz.files import inside_folder, write_json

NEAR, FAR = 2.0, 6.0
BBOX = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])


def _image_path(root: Path, file_path: str, listed_in: str) -> Path:
    p = inside_folder(root, file_path, listed_in)
    if p.suffix.lower() in (".png", ".jpg", ".jpeg"):
        return p
    return p.with_name(p.name + ".png")


def load_blender(
    path: str | os.PathLike, split: str = "test", res: int | None = None, indices: Iterable[int] | None = None
) -> SceneData:
    """Read a Blender-format folder's `split` orbit; optionally downscale to width `res`.

    `indices` restricts which orbit indices are loaded (default: all frames).
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"scene folder not found: {root}")
    jpath = root / f"transforms_{split}.json"
    if not jpath.is_file():
        raise DatasetError(f"{jpath.name} not found in {root}")
    meta = read_transforms(jpath)
    check_resolution(res)

    try:
        angle_x = float(meta["camera_angle_x"])
        if not isinstance(meta["frames"], list):
            raise ValueError(f"'frames' is a JSON {type(meta['frames']).__name__}, not a list of frames")
        frames = list(meta["frames"])
        if not frames:
            raise ValueError("no frames")
        entries = []
        for k, fr in enumerate(frames):
            if not isinstance(fr, dict):
                raise ValueError(f"frame {k} is a JSON {type(fr).__name__}, not an object")
            c2w = camera_to_world(fr["transform_matrix"], k)
            entries.append((int(fr["orbit_index"]) if "orbit_index" in fr else k, str(fr["file_path"]), c2w))
    except (KeyError, TypeError, ValueError) as e:
        what = f"missing key {e}" if isinstance(e, KeyError) else str(e).splitlines()[0]
        raise DatasetError(f"{jpath} is malformed: {what}") from None
    if not all("orbit_index" in fr for fr in frames):  # all or nothing: else frame order
        entries = [(k, fp, c2w) for k, (_, fp, c2w) in enumerate(entries)]
    if not (0.0 < angle_x < np.pi):
        raise DatasetError(f"{jpath} is malformed: camera_angle_x = {angle_x} is not in (0, pi)")
    if len({i for i, _, _ in entries}) != len(entries):
        raise DatasetError(f"{jpath} is malformed: repeated orbit_index")
    if indices is not None:
        keep = {int(i) for i in indices}
        entries = [e for e in entries if e[0] in keep]

    views: dict[int, View] = {}
    size = None
    for index, file_path, c2w in entries:
        ipath = _image_path(root, file_path, jpath.name)
        if not os.path.isfile(ipath):  # False, not an error, for a name the system refuses (too long)
            raise DatasetError(f"image {ipath} listed in {jpath.name} not found")
        rgba = read_rgba(ipath)
        check_width(res, rgba.shape[1], root)
        if size is None:
            size = rgba.shape[:2]
        elif rgba.shape[:2] != size:
            raise DatasetError(
                f"images have inconsistent sizes: {ipath.name} is {rgba.shape[1]}x{rgba.shape[0]}, "
                f"expected {size[1]}x{size[0]}"
            )
        rgb, alpha = composite_on_white(rgba, res)
        H, W = rgb.shape[:2]
        focal = 0.5 * W / np.tan(0.5 * angle_x)
        views[index] = View(Camera(c2w, W, H, float(focal), name=Path(file_path).name), rgb, alpha, index=index)

    return SceneData(
        name=root.name,
        views=views,
        near=NEAR,
        far=FAR,
        bbox=BBOX.copy(),
        symmetry_plane=None,
        source=str(root),
        meta={"split": split, "camera_angle_x": angle_x},
    )


def write_blender(scene: SceneData, out_dir: str | os.PathLike, split: str = "test") -> Path:
    """Write `scene` as a Blender-format folder (8-bit RGBA PNGs + transforms_{split}.json)."""
    out = Path(out_dir)
    (out / split).mkdir(parents=True, exist_ok=True)
    idx = sorted(scene.views)
    contiguous = idx == list(range(len(idx)))
    frames = []
    for i in idx:
        name = f"r_{i}"
        save_rgba_png(out / split / f"{name}.png", uncomposite(scene.views[i].rgb, scene.views[i].alpha))
        frame = {"file_path": f"./{split}/{name}", "transform_matrix": scene.views[i].camera.c2w.tolist()}
        if not contiguous:
            frame["orbit_index"] = i
        frames.append(frame)
    first = scene.views[idx[0]].camera
    doc = {"camera_angle_x": first.fov_x, "frames": frames}
    write_json(out / f"transforms_{split}.json", doc)
    return out


def export_scene(name: str, out_dir: str | os.PathLike, res: int = 100) -> Path:
    """Write built-in scene `name` (the full first turn, orbit indices 0..99) in Blender format."""
    from flipviz.data.builtin import load_builtin  # local import: builtin is the heavier module

    return write_blender(load_builtin(name, res, indices=range(100)), out_dir, split="test")
