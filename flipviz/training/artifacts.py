"""What a run leaves in its folder besides the checkpoint: metrics, test renders, refined poses.

<run folder>/metrics.json            PSNR / SSIM / LPIPS on the unobserved views (evaluate.py)
<run folder>/test_renders/<view>.png and <view>_gt.png
<run folder>/transforms.json         the refined mirrored poses, Blender format, with
<run folder>/mirrored/<view>.png     their flipped images
<run folder>/plane.json              --mirror-plane auto: the estimated plane, its confidence
                                     and scores (read back when the run is resumed)
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from flipviz.data.cameras import Camera
from flipviz.data.images import save_png
from flipviz.errors import UserError
from flipviz.files import FolderLock, remove_leftover_temps, write_json
from flipviz.geometry.symmetry import PlaneEstimate
from flipviz.training.checkpoint import CHECKPOINT_NAME, load_checkpoint
from flipviz.training.config import TrainConfig

log = logging.getLogger("flipviz.training")

PLANE_FILE, METRICS_FILE = "plane.json", "metrics.json"
RUN_FILES = (CHECKPOINT_NAME, METRICS_FILE, "transforms.json", PLANE_FILE, "test_renders", "mirrored", "recording*.rrd")


def holds_run(run_dir: Path) -> bool:
    """A folder where a run has trained (its checkpoint) or ended (its metrics)."""
    return (run_dir / CHECKPOINT_NAME).is_file() or (run_dir / METRICS_FILE).is_file()


def refuse_to_overwrite(run_dir: Path, cfg: TrainConfig) -> None:
    """One UserError line instead of a silent overwrite: a fresh run (no --resume) over an earlier
    run without --overwrite, or a --rrd in the folder of a run that another process trains."""
    if cfg.output.resume is None and not cfg.output.overwrite and holds_run(run_dir):
        raise UserError(
            f"{run_dir} holds an earlier run; continue it with --resume {run_dir}, "
            "replace it with --overwrite, or choose another --out"
        )
    rrd = None if cfg.output.no_rrd or cfg.output.rrd is None else Path(cfg.output.rrd)
    if rrd is not None and rrd.parent.resolve() != run_dir.resolve() and (holder := FolderLock.holder(rrd.parent)):
        raise UserError(
            f"the recording {rrd} would go into the run folder {rrd.parent}, which {holder} is training; "
            "choose another --rrd"
        )


def check_named_files(cfg: TrainConfig) -> None:
    """The files a user named, checked before any heavy work (loading or rendering a scene, a plane fit),
    each a one-line UserError: --resume a readable checkpoint, --rrd a file that can be written."""
    if cfg.output.resume is not None:
        load_checkpoint(cfg.output.resume)
    if not cfg.output.no_rrd and cfg.output.rrd is not None:
        check_recording_target(Path(cfg.output.rrd))


def check_recording_target(path: Path) -> None:
    """A recording can be written at `path` (a .rrd file; its folder made), else one UserError line."""
    if path.is_dir():
        raise UserError(f"cannot write the recording {path}: it is a folder (name a .rrd file)")
    folder = next((p for p in path.absolute().parents if p.exists()), Path("/"))  # the nearest that exists
    if not folder.is_dir() or not os.access(folder, os.W_OK):
        raise UserError(f"cannot write the recording {path}: {folder} is not a folder it can write in")


def remove_run(run_dir: Path) -> None:
    """Delete what an earlier run wrote in `run_dir` (--overwrite), and nothing else there."""
    for pattern in RUN_FILES:
        for p in run_dir.glob(pattern):
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)


def prune_checkpoints(run_dirs: list[Path], budget_bytes: float) -> list[Path]:
    """Keep the checkpoints of the newest run folders (`run_dirs` oldest first) within `budget_bytes`
    in all and delete the older ones (metrics, renders and recordings stay). Returns those deleted."""
    kept, deleted = 0, []
    for run_dir in reversed(run_dirs):
        ckpt = run_dir / CHECKPOINT_NAME
        if not ckpt.is_file():
            continue
        size = ckpt.stat().st_size
        if kept + size <= budget_bytes:
            kept += size
        else:
            ckpt.unlink(missing_ok=True)
            deleted.append(ckpt)
    return deleted


def write_test_renders(run_dir: Path, names: list[str], preds: list[np.ndarray], gts: list[np.ndarray]) -> None:
    for name, pred, gt in zip(names, preds, gts, strict=True):
        save_png(run_dir / "test_renders" / f"{name}.png", pred)
        save_png(run_dir / "test_renders" / f"{name}_gt.png", gt)


def write_metrics(run_dir: Path, metrics: dict) -> Path:
    return write_json(run_dir / METRICS_FILE, metrics)


def write_transforms(
    run_dir: Path, cameras: list[Camera], images: list[np.ndarray], image_dir: str = "mirrored"
) -> Path:
    """Blender-format transforms.json of `cameras` (the refined mirrored poses) + their PNG images."""
    frames = []
    for i, (cam, img) in enumerate(zip(cameras, images, strict=True)):
        rel = f"./{image_dir}/{cam.name or f'mirror_{i:02d}'}"
        save_png(run_dir / (rel + ".png"), img)
        frames.append({"file_path": rel, "transform_matrix": np.asarray(cam.c2w).tolist()})
    data = {"camera_angle_x": float(cameras[0].fov_x) if cameras else 0.0, "frames": frames}
    return write_json(run_dir / "transforms.json", data)


def write_plane(run_dir: Path, estimate: PlaneEstimate) -> Path:
    return write_json(run_dir / PLANE_FILE, estimate.to_dict())


def take_over(run_dir: Path, cfg: TrainConfig) -> None:
    """Holding the run folder's lock: remove the temporary files of killed writes, and refuse to
    overwrite an earlier run (unless --overwrite, which deletes it) or another run's recording."""
    if remove_leftover_temps(run_dir):
        log.info("removed the temporary files of writes killed earlier in %s", run_dir)
    refuse_to_overwrite(run_dir, cfg)
    if cfg.output.resume is None and cfg.output.overwrite:
        remove_run(run_dir)
