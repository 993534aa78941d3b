"""Read and write nerfstudio captures: one `transforms.json` and its images.

The format (docs.nerf.studio, "Data conventions"): intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`
at the top level or per frame (a frame's own keys win), `camera_model` PINHOLE, SIMPLE_PINHOLE or
OPENCV (`k1`, `k2`, `p1`, `p2`, optional `k3`); `frames`, each with `file_path`, `transform_matrix`
(4x4 OpenGL camera-to-world, the flipviz convention) and an optional `mask_path`; optional
`train_filenames` / `test_filenames` (the capture's own split), `ply_file_path` (sparse points,
already in the frame of the poses), `applied_transform` (the 3x4 transform nerfstudio's processing
applied to the original poses; read, checked and kept in `meta`), `aabb_scale`, and flipviz's own
`flipviz_symmetry_plane` (the true plane of an exported built-in scene, for measurement).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from flipviz.data.cameras import View
from flipviz.data.capture import Intrinsics, capture_view, make_capture
from flipviz.data.dataset import DatasetError, Plane, SceneData, camera_to_world, check_resolution, read_transforms
from flipviz.data.images import save_rgba_png, uncomposite
from flipviz.files import inside_folder, write_json

MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
OPENCV_KEYS = ("k1", "k2", "p1", "p2")


def _intrinsics(d: dict, top: dict, model: str, where: str) -> Intrinsics:
    """A frame's intrinsics: its own keys, else the file's."""
    get = lambda k, default=None: d.get(k, top.get(k, default))  # noqa: E731
    fx = get("fl_x")
    if fx is None:
        raise KeyError("fl_x")
    w, h = int(get("w")), int(get("h"))
    dist: tuple[float, ...] = ()
    if model == "OPENCV":
        dist = tuple(float(get(k, 0.0)) for k in OPENCV_KEYS) + ((float(get("k3")),) if get("k3") is not None else ())
    return Intrinsics(
        w, h, float(fx), float(get("fl_y", fx)), float(get("cx", w / 2)), float(get("cy", h / 2)), dist
    ).check(where)


def _ply_points(path: Path) -> np.ndarray:
    import trimesh

    try:
        return np.asarray(trimesh.load(path, process=False).vertices, dtype=np.float64)
    except Exception as e:
        raise DatasetError(f"cannot read the sparse points {path} ({type(e).__name__})") from None


def load_nerfstudio(path: str | os.PathLike, res: int | None = None) -> SceneData:
    """A nerfstudio capture (a folder with transforms.json, or the file itself) at width `res`."""
    p = Path(path)
    jpath = p / "transforms.json" if p.is_dir() else p
    if not jpath.is_file():
        raise DatasetError(f"transforms.json not found in {p}")
    root = jpath.parent
    meta = read_transforms(jpath)
    check_resolution(res)

    try:
        model = str(meta.get("camera_model", "OPENCV" if any(k in meta for k in OPENCV_KEYS) else "PINHOLE"))
        if model not in MODELS:
            raise ValueError(f"camera_model {model} is not supported (flipviz reads {', '.join(MODELS)})")
        frames = meta["frames"]
        if not isinstance(frames, list) or not frames:
            raise ValueError("'frames' is not a non-empty list")
        entries = []
        for k, fr in enumerate(frames):
            if not isinstance(fr, dict):
                raise ValueError(f"frame {k} is a JSON {type(fr).__name__}, not an object")
            frame_model = str(fr.get("camera_model", model))
            if frame_model not in MODELS:  # a frame's own model, like the file's: never trained as a pinhole
                raise ValueError(
                    f"frame {k}: camera_model {frame_model} is not supported (flipviz reads {', '.join(MODELS)})"
                )
            intr = _intrinsics(fr, meta, frame_model, f"{jpath} frame {k}")
            entries.append(
                (str(fr["file_path"]), camera_to_world(fr["transform_matrix"], k), intr, fr.get("mask_path"))
            )
        applied = meta.get("applied_transform")
        if applied is not None:
            A = np.asarray(applied, dtype=np.float64)
            if A.shape not in ((3, 4), (4, 4)) or not np.isfinite(A).all():
                raise ValueError("applied_transform is not a finite 3x4 matrix")
        aabb = meta.get("aabb_scale")
        if aabb is not None and not (np.isfinite(float(aabb)) and float(aabb) > 0):
            raise ValueError(f"aabb_scale = {aabb} is not a positive number")
    except (KeyError, TypeError, ValueError, OverflowError) as e:  # OverflowError: a size of 1e999
        what = f"missing key {e}" if isinstance(e, KeyError) else str(e).splitlines()[0]
        raise DatasetError(f"{jpath} is malformed: {what}") from None

    views: dict[int, View] = {}
    by_file: dict[str, int] = {}
    for k, (file_path, c2w, intr, mask_path) in enumerate(entries):
        mask = inside_folder(root, str(mask_path), jpath.name) if mask_path is not None else None
        views[k] = capture_view(inside_folder(root, file_path, jpath.name), mask, intr, c2w, res, k, jpath.name)
        by_file[file_path] = by_file[file_path.lstrip("./")] = k

    splits: dict[str, list[int]] = {}
    for split in ("train", "test"):
        names = meta.get(f"{split}_filenames")
        if names is not None and not isinstance(names, list):
            raise DatasetError(f"{jpath} is malformed: {split}_filenames is a JSON {type(names).__name__}, not a list")
        if names is not None:
            unknown = [n for n in names if str(n) not in by_file and str(n).lstrip("./") not in by_file]
            if unknown:
                raise DatasetError(f"{jpath} is malformed: {split}_filenames lists {unknown[0]!r}, not a frame")
            splits[split] = sorted({by_file.get(str(n), by_file.get(str(n).lstrip("./"), -1)) for n in names})
    points = (
        _ply_points(inside_folder(root, str(meta["ply_file_path"]), jpath.name)) if meta.get("ply_file_path") else None
    )
    extra = {"format": "nerfstudio", "camera_model": model}
    if meta.get("applied_transform") is not None:
        extra["applied_transform"] = np.asarray(meta["applied_transform"], dtype=np.float64).tolist()
    scene = make_capture(root.name, views, str(root), splits, points, meta.get("aabb_scale"), extra)
    if "flipviz_symmetry_plane" in meta:  # written by `flipviz export-scene --trajectory driveby`
        try:
            scene.symmetry_plane = Plane.from_dict(meta["flipviz_symmetry_plane"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{jpath} is malformed: flipviz_symmetry_plane is not a point and a normal") from None
    return scene


def write_nerfstudio(
    views: list[View], out_dir: str | os.PathLike, splits: dict[str, list[int]] | None = None, extra: dict | None = None
) -> Path:
    """Write views as a nerfstudio capture: RGBA PNGs (alpha = mask) and transforms.json (PINHOLE)."""
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    cam0 = views[0].camera
    frames = []
    for k, v in enumerate(views):
        name = f"images/frame_{k:05d}.png"
        save_rgba_png(out / name, uncomposite(v.rgb, v.alpha))
        frames.append({"file_path": name, "transform_matrix": v.camera.c2w.tolist()})
    doc = {
        "camera_model": "PINHOLE",
        "fl_x": cam0.focal,
        "fl_y": cam0.focal,
        "cx": cam0.width / 2,
        "cy": cam0.height / 2,
        "w": cam0.width,
        "h": cam0.height,
        **(extra or {}),
        "frames": frames,
    }
    for split, idx in (splits or {}).items():
        doc[f"{split}_filenames"] = [frames[i]["file_path"] for i in idx]
    write_json(out / "transforms.json", doc)
    return out
