"""Videos of runs along a camera path: render | ground truth | |error| | beta^2, one row per run.

    flipviz video runs/chair-flip+u-1-... --path unobserved          -> <run>/video_unobserved.mp4
    flipviz video RUN_BL RUN_FLIPU --path orbit --gif docs/orbit.gif  (A/B: one row each, same cameras)

The MP4 is written by imageio's ffmpeg plugin (imageio-ffmpeg ships its own ffmpeg binary), the GIF
by Pillow; both through a temporary file renamed into place, so an interrupted video leaves no
half file and never replaces an older one. Ground truth: built-in scenes are ray cast from any
camera; a dataset has it where a frame lands on one of its views (the unobserved path's test views).
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import tyro

from flipviz.data import load_scene
from flipviz.data.builtin import builtin_name, render_view
from flipviz.data.cameras import Camera
from flipviz.data.dataset import SceneData
from flipviz.data.images import to_uint8
from flipviz.errors import UserError
from flipviz.files import atomic_path, cannot_write
from flipviz.options import Range, check_ranges
from flipviz.training.config import METHOD_LABELS
from flipviz.training.evaluate import image_psnr
from flipviz.training.events import SetupEvent
from flipviz.viz import palette
from flipviz.viz.camera_path import keyframe_path, orbit_path, read_keyframes, unobserved_path
from flipviz.viz.images import error_map

PANELS = ("render", "ground truth", "|error|", "beta^2")
TITLE_H = 22  # pixels of the caption strip above each row
Render = Callable[[Camera], dict]  # camera -> {"rgb", "beta2", ...} (Trainer.render, App.render)


@dataclass
class VideoConfig:
    """Render a run (or two, A/B) along a camera path to an MP4, optionally a GIF too."""

    runs: Annotated[list[Path], tyro.conf.Positional]
    """One run folder, or two to compare (one row each, the same cameras)."""
    path: str = "unobserved"
    """orbit (all round) | unobserved (through the held-out views) | a keyframes.json from the app
    (Compare tab) or a nerfstudio camera_path.json."""
    frames: Annotated[int, Range(2, 10_000)] = 100
    """Frames of the path (the unobserved path rounds it so that a frame lands on every test view)."""
    res: Annotated[int, Range(16, 2048)] = 200
    """Width in pixels of each panel."""
    fps: Annotated[int, Range(1, 120)] = 24
    out: Path | None = None
    """MP4 to write (default <first run>/video_<path>.mp4)."""
    gif: Path | None = None
    """Also write a GIF (every second frame, panels at most 160 px wide), e.g. for a README."""
    device: str | None = None
    """cpu | cuda | cuda:N (default: the device the run trained on)."""

    def validate(self) -> VideoConfig:
        if not 1 <= len(self.runs) <= 2:
            raise UserError(f"flipviz video takes one run folder, or two to compare; got {len(self.runs)}")
        check_ranges(self)
        return self


def path_cameras(setup: SetupEvent, path: str, frames: int, res: int) -> list[Camera]:
    """The cameras of `path` (orbit | unobserved | a keyframes file) at `res` pixels wide."""
    if path == "orbit":
        cams = orbit_path(setup, frames)
    elif path == "unobserved":
        cams = unobserved_path(setup, frames)
    else:
        cams = keyframe_path(setup, read_keyframes(path, res), frames)
    return [c.resized(res) for c in cams]


class GroundTruth:
    """The true image seen from a camera, where one is known: built-ins anywhere (ray cast), a
    dataset at its own views (same pose), loaded at the video's resolution."""

    def __init__(self, scene: SceneData, loader: Callable[[int], SceneData] | None = None) -> None:
        self.builtin = builtin_name(scene)
        self._scene, self._loader, self._by_res = scene, loader, {}

    @classmethod
    def of_run(cls, trainer) -> GroundTruth:
        """A run's ground truth, its dataset reloaded at another width when a camera asks for one."""
        return cls(trainer.scene, lambda width: load_scene(trainer.cfg.data.scene, trainer.cfg.data.path, width))

    def __call__(self, cam: Camera) -> np.ndarray | None:
        if self.builtin is not None:
            return render_view(self.builtin, cam)[0]
        scene = self._scene_at(cam.width)
        scale = float(np.linalg.norm(scene.bbox[1] - scene.bbox[0]))
        for v in scene.views.values():
            c = v.camera
            if (c.width, c.height) == (cam.width, cam.height) and np.allclose(c.c2w, cam.c2w, atol=1e-6 * scale):
                return v.rgb
        return None

    def _scene_at(self, width: int) -> SceneData:
        if width == self._scene.resolution[0] or self._loader is None:
            return self._scene
        if width not in self._by_res:
            try:
                self._by_res[width] = self._loader(width)
            except UserError:  # wider than the data: no ground truth at this width
                self._by_res[width] = self._scene
        return self._by_res[width]


def _caption(text: str, width: int) -> np.ndarray:
    strip = np.full((TITLE_H, width, 3), 255, np.uint8)
    cv2.putText(strip, text, (4, TITLE_H - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (30, 30, 30), 1, cv2.LINE_AA)
    return strip


def _blank(h: int, w: int, text: str) -> np.ndarray:
    img = np.full((h, w, 3), 235, np.uint8)
    cv2.putText(img, text, (6, h // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (120, 120, 120), 1, cv2.LINE_AA)
    return img


def compose_row(label: str, out: dict, gt: np.ndarray | None) -> np.ndarray:
    """One run's row: its label (and PSNR where the ground truth is known) across the row, then
    render | ground truth | |error| | beta^2, each with its caption (uint8 RGB)."""
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    h, w = rgb.shape[:2]
    beta2 = out.get("beta2")
    panels = [
        to_uint8(rgb),
        to_uint8(gt) if gt is not None else _blank(h, w, "no ground truth"),
        error_map(rgb, gt) if gt is not None else _blank(h, w, "no ground truth"),
        palette.colormap(beta2, *palette.BETA2_RANGE) if beta2 is not None else _blank(h, w, "no beta^2"),
    ]
    captions = ["render", "ground truth", f"|error| 0-{palette.ERROR_RANGE[1]}", f"beta^2 0-{palette.BETA2_RANGE[1]}"]
    psnr = f"   PSNR {image_psnr(rgb, gt):.2f} dB" if gt is not None else ""
    row = np.concatenate([np.concatenate([_caption(c, w), p]) for c, p in zip(captions, panels)], axis=1)
    return np.concatenate([_caption(label + psnr, row.shape[1]), row])


def compose_frame(rows: list[tuple[str, dict]], gt: np.ndarray | None) -> np.ndarray:
    """All runs' rows stacked, padded to even sizes (what H.264 needs)."""
    frame = np.concatenate([compose_row(label, out, gt) for label, out in rows], axis=0)
    pad_h, pad_w = (-frame.shape[0]) % 16, (-frame.shape[1]) % 16
    return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), constant_values=255)


def render_frames(
    renders: list[tuple[str, Render]],
    cameras: list[Camera],
    ground_truth: Callable[[Camera], np.ndarray | None],
    progress: bool = True,
) -> Iterator[np.ndarray]:
    """One composed frame per camera (render each run, the ground truth where known), as rendered."""
    from tqdm import tqdm

    for cam in tqdm(cameras, desc="video", unit="frame", disable=not progress, dynamic_ncols=True):
        rows = [(label, render(cam)) for label, render in renders]
        yield compose_frame(rows, ground_truth(cam))


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: int) -> Path:
    """H.264 MP4 through imageio-ffmpeg, frames written as they come. The file appears whole or not at
    all: it is decoded back before it replaces an earlier one (ffmpeg on a full disk leaves a file it
    cannot open, and imageio raises nothing)."""
    import imageio.v2 as imageio

    with cannot_write(path, "the video"), atomic_path(path) as tmp:
        try:
            with imageio.get_writer(
                tmp, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=16, ffmpeg_log_level="quiet"
            ) as w:
                n, shape = 0, None
                for f in frames:
                    w.append_data(f)
                    n, shape = n + 1, f.shape
        except OSError as e:  # imageio's message holds ffmpeg's whole command line
            why = f" ({os.strerror(e.errno)})" if e.errno else ""
            raise OSError(e.errno or errno.EIO, f"ffmpeg stopped writing{why}") from None
        check_video(tmp, n, shape)
    return Path(path)


def check_video(path: Path, frames: int, shape: tuple[int, ...] | None) -> None:
    """An OSError unless `path` decodes to `frames` frames of `shape` (H, W, 3)."""
    import imageio.v2 as imageio
    from imageio_ffmpeg import count_frames_and_secs

    try:
        with imageio.get_reader(path, format="FFMPEG") as r:
            first = r.get_data(0)
        counted = count_frames_and_secs(str(path))[0]
    except Exception as e:  # imageio and ffmpeg raise many kinds for a broken file
        raise OSError(errno.EIO, f"the written video does not decode ({type(e).__name__}); is the disk full?") from None
    if frames and (counted != frames or first.shape != shape):
        raise OSError(errno.EIO, f"the written video has {counted} frames of {first.shape}, not {frames} of {shape}")


class GifFrames:
    """Keeps every `step`-th frame of a stream, shrunk so that a panel is at most `max_panel` pixels wide."""

    def __init__(self, step: int = 2, max_panel: int = 160) -> None:
        self.step, self.max_panel, self.frames = step, max_panel, []
        self._seen = 0

    def keep(self, frames: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        from PIL import Image

        for f in frames:
            if self._seen % self.step == 0:
                scale = min(1.0, self.max_panel * len(PANELS) / f.shape[1])
                size = (round(f.shape[1] * scale), round(f.shape[0] * scale))
                self.frames.append(Image.fromarray(f).resize(size, Image.LANCZOS))
            self._seen += 1
            yield f

    def gif_bytes(self, fps: float) -> bytes:
        """The kept frames as a looping GIF at fps / step."""
        import io

        buf = io.BytesIO()
        first, rest = self.frames[0], self.frames[1:]
        first.save(buf, format="GIF", save_all=True, append_images=rest, duration=round(1000 * self.step / fps), loop=0)
        return buf.getvalue()

    def write(self, path: Path, fps: float) -> Path:
        """The GIF, written whole or not at all."""
        with cannot_write(path, "the GIF"), atomic_path(path) as tmp:
            tmp.write_bytes(self.gif_bytes(fps))
        return Path(path)


def make_video(cfg: VideoConfig) -> tuple[Path, Path | None]:
    """`flipviz video`: open the runs, render the path, write the MP4 (and the GIF)."""
    from flipviz.training.saved_run import open_run
    from flipviz.training.trainer import scene_label

    cfg.validate()
    runs = [open_run(r, cfg.device) for r in cfg.runs]
    a = runs[0]
    if len(runs) == 2 and runs[1].scene.name != a.scene.name:
        raise UserError(
            f"the runs show different scenes ({a.scene.name}, {runs[1].scene.name}); compare runs of one scene"
        )
    cameras = path_cameras(a.setup_event, cfg.path, cfg.frames, cfg.res)
    gt = GroundTruth.of_run(a)
    labels = [f"{METHOD_LABELS[r.cfg.method]} ({scene_label(r.cfg)}, {r.step} steps)" for r in runs]
    small = GifFrames(step=2 if len(cameras) > 40 else 1)
    name = "keyframes" if cfg.path not in ("orbit", "unobserved") else cfg.path
    with contextlib.closing(
        render_frames([(label, r.render) for label, r in zip(labels, runs)], cameras, gt)
    ) as frames:
        out = write_mp4(cfg.out or a.run_dir / f"video_{name}.mp4", small.keep(frames) if cfg.gif else frames, cfg.fps)
    gif = small.write(cfg.gif, cfg.fps) if cfg.gif is not None else None
    return out, gif
