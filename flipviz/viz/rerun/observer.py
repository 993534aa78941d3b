"""Stream a training run to Rerun: a `.rrd` recording, and optionally a local web viewer.

`RerunObserver` turns the trainer's events (`flipviz.training.events`) into Rerun entities on one
`step` timeline (layout in `flipviz.viz.rerun.blueprint`). It logs through its own
`rr.RecordingStream` (never the global one) and sets the time on the calling thread before every
log, so it is safe to call from the training thread. The file is written incrementally and flushed
every few seconds, so a killed run still leaves a readable recording; `on_end` finalises it and
compacts it (`optimize_recording`): the live log is many small chunks, which viewers open slowly.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import rerun as rr

from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane
from flipviz.data.images import to_uint8
from flipviz.errors import UserError
from flipviz.files import free_bytes, next_free, signals_deferred
from flipviz.training.artifacts import check_recording_target
from flipviz.training.config import TrainConfig
from flipviz.training.events import (
    CameraInfo,
    EndEvent,
    ImagesEvent,
    Observer,
    RenderedView,
    SetupEvent,
    StepEvent,
    split_label,
)
from flipviz.viz import palette
from flipviz.viz.rerun.blueprint import STEP, entity_name, make_blueprint
from flipviz.viz.rerun.viewer import RerunWebViewer
from flipviz.viz.splats import solid_splats

APP_ID = "flipviz"
log = logging.getLogger("flipviz.rerun")

COLORS = palette.CAMERA  # the app's colours: the same thing looks the same in both


@dataclass
class RerunOptions:
    """How a run is recorded."""

    path: Path | None  # .rrd file (None: no file, only the viewer)
    serve: bool = False  # also serve a local web viewer (127.0.0.1) and print its URL
    web_port: int = 9090  # preferred ports (a free one is picked when taken)
    grpc_port: int = 9876
    jpeg_quality: int = 85  # for the RGB images
    max_map_size: int = 128  # scalar maps (beta^2, depth, opacity, error) are strided down to this
    step_stride: int = 1  # log every n-th StepEvent (on top of cfg.output.log_every)
    flush_every_s: float = 2.0
    min_free_mb: float = 32.0  # the recording stops (and stays readable) when its disk has less free
    optimize: bool = True  # compact the finished file's chunks (optimize_recording)
    # beta^2 colour range, fixed for the whole run so frames compare (raw values are stored unclipped).
    # Its floor is beta_min^2 = 0.01; at the NLL optimum beta^2 = ||C - C_hat||^2 (Sec. IV-C), and on the
    # chair most symmetry-breaking pixels stay below 0.1 (measured, step 700 at 48 px).
    beta2_range: tuple[float, float] = palette.BETA2_RANGE
    error_max: float = palette.ERROR_RANGE[1]  # colour range of the |render - GT| map
    splats_every: int = 4  # the field as Gaussian splats at every n-th ImagesEvent and at the end (0: never)


def camera_paths(cameras: list[CameraInfo]) -> list[str]:
    """Entity path of each camera: world/cameras/<kind>/<name>, made unique within a kind."""
    paths, seen = [], set()
    for i, info in enumerate(cameras):
        p = f"world/cameras/{info.kind}/{entity_name(info.camera.name)}"
        if p in seen or not info.camera.name:
            p = f"world/cameras/{info.kind}/{info.kind}_{i}"
        seen.add(p)
        paths.append(p)
    return paths


AGREEMENT_SCALARS = ("disagreement", "mse_mirror", "mse_input", "mirrors_trained")  # training/flip.py: Agreement


class RerunObserver(Observer):
    """Logs a run's setup, steps, periodic renders and end to a Rerun recording stream."""

    def __init__(self, opts: RerunOptions, bake: Callable[[], dict] | None = None) -> None:
        """`bake`: the trainer's `point_cloud` (the field's cells), logged as splats at a few steps."""
        self.opts, self._bake = opts, bake
        self._n_images, self._splats_step = 0, -1
        self.rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
        self.viewer: RerunWebViewer | None = None
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self._n_step_events = 0
        self._mirror_names: list[str] = []
        self._prev_centers: np.ndarray | None = None
        self._dropped: set[int] = set()  # the mirrors whose drop is logged
        self._depth_range = (0.0, 10.0)
        self._logged_gt: set[str] = set()
        self._sinks_ready = False
        self._closed = False
        self._file_stopped = False  # the disk was nearly full: the file was finalised early
        self._frustum_scale = 0.3
        self._scalars: dict[str, tuple[list[int], list[np.ndarray]]] = {}  # per entity: steps, values (not yet sent)
        self._poses: dict[
            str, tuple[list[int], list[np.ndarray]]
        ] = {}  # per mirrored camera: steps, c2w (not yet sent)
        self._plane_size, self._plane_moves = 1.0, False  # set by the SetupEvent
        self._moving_planes: set[str] = set()  # planes whose shape is logged (in their own frame)
        self._series_colors = [tuple(int(255 * c) for c in rgb[:3]) for rgb in matplotlib.colormaps["tab10"].colors]

    # ------------------------------------------------------------------ sinks
    def _attach_sinks(self, blueprint: rr.blueprint.Blueprint) -> None:
        """File sink (+ gRPC to a local viewer); called once the camera names are known."""
        sinks: list = []
        if self.opts.path is not None:
            self.opts.path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.opts.path)))
        if self.opts.serve:
            self.viewer = RerunWebViewer.start(self.opts.grpc_port, self.opts.web_port)
            print(f"Rerun web viewer: {self.viewer.url}", flush=True)
            sinks.append(rr.GrpcSink(self.viewer.grpc_url))
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=blueprint)
        self._sinks_ready = True

    @staticmethod
    def _hold(held: dict[str, tuple[list[int], list[np.ndarray]]], path: str, step: int, value: np.ndarray) -> None:
        """A step's value of an entity, held back until `_send_columns` sends the entity's values as one
        column: a few large chunks instead of one per step and entity."""
        steps, values = held.setdefault(path, ([], []))
        steps.append(int(step))
        values.append(value)

    def _scalar(self, path: str, step: int, value) -> None:
        """A step's scalar (or one per mirror), held back (`_hold`)."""
        self._hold(self._scalars, path, step, np.atleast_1d(np.asarray(value, np.float64)))

    def _send_columns(self) -> None:
        """Send the held-back curves and mirrored poses, one column per entity."""
        for path, (steps, values) in self._scalars.items():
            if steps and len({len(v) for v in values}) == 1:  # one width per entity (the mirrors do not change)
                self.rec.send_columns(
                    path,
                    indexes=[rr.TimeColumn(STEP, sequence=steps)],
                    columns=rr.Scalars.columns(scalars=np.stack(values)),
                )
        for path, (steps, poses) in self._poses.items():
            T = np.stack(poses)  # (N, 4, 4) camera-to-world
            self.rec.send_columns(
                path,
                indexes=[rr.TimeColumn(STEP, sequence=steps)],
                columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]),
            )
        self._scalars, self._poses = {}, {}

    def _maybe_flush(self, force: bool = False) -> None:
        if force or time.monotonic() - self._last_flush >= self.opts.flush_every_s:
            self._send_columns()
            try:
                self.rec.flush(timeout_sec=5.0)
            except Exception:  # a slow disk or viewer must not stop training
                pass
            self._last_flush = time.monotonic()
            self._stop_file_before_the_disk_fills()

    def _stop_file_before_the_disk_fills(self) -> None:
        """A full disk cuts Rerun's file writer mid-chunk, leaving a file no reader scans. So below
        `min_free_mb` the file is finalised (footer written, readable) and recording to it stops;
        a served viewer goes on receiving."""
        path = self.opts.path
        if path is None or self._file_stopped or free_bytes(path) >= self.opts.min_free_mb * 1e6:
            return
        self._file_stopped = True
        if self.viewer is not None:
            self.rec.set_sinks(rr.GrpcSink(self.viewer.grpc_url))  # the file sink is finalised and dropped
        else:
            self.rec.disconnect()  # finalises the file; nothing is logged after (see `_silent`)
        log.warning(
            "the recording %s stops here: its disk has less than %.0f MB free; what it holds stays readable",
            path,
            self.opts.min_free_mb,
        )

    @property
    def _silent(self) -> bool:
        """The file was finalised early (disk nearly full) and no viewer listens: nothing to log to."""
        return self._file_stopped and self.viewer is None

    def _shrink(self, a: np.ndarray) -> np.ndarray:
        """Integer-stride a map down to at most max_map_size pixels a side (float16 storage)."""
        s = max(1, int(np.ceil(max(a.shape[:2]) / self.opts.max_map_size)))
        return np.asarray(a[::s, ::s], dtype=np.float16)

    def _map(self, a: np.ndarray, colormap: str, lo: float, hi: float) -> rr.DepthImage:
        # Raw values stay readable back (float16); the colour range is fixed for the whole run.
        return rr.DepthImage(self._shrink(a), meter=1.0, colormap=colormap, depth_range=[lo, hi])

    def _jpeg(self, img: np.ndarray) -> rr.EncodedImage | rr.Image:
        return rr.Image(to_uint8(img)).compress(jpeg_quality=self.opts.jpeg_quality)

    # ------------------------------------------------------------------ events
    def on_setup(self, event: SetupEvent) -> None:
        with self._lock:
            tests = [c.camera.name for c in event.cameras if c.kind == "test"]
            # Refined mirrored cameras exist only when the method trains on mirrors (plane given).
            mirrors = [c.camera.name for c in event.cameras if c.kind == "mirror_init"] if event.plane else []
            if not self._sinks_ready:
                self._attach_sinks(make_blueprint(tests, mirrors, event.sphere_center, float(event.sphere_radius)))
            self._mirror_names = [entity_name(n) for n in mirrors]
            self._log_setup(event)
            self._maybe_flush(force=True)

    def _log_setup(self, e: SetupEvent) -> None:
        rec = self.rec
        r = float(e.sphere_radius)
        c = np.asarray(e.sphere_center, dtype=np.float64)
        self._depth_range = (e.near, e.far)

        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(
            "world/sphere",
            rr.Ellipsoids3D(
                centers=[c],
                half_sizes=[[r, r, r]],
                colors=[palette.SPHERE],
                fill_mode="majorwireframe",
                line_radii=0.004,
                labels=["least-squares sphere"],
            ),
            static=True,
        )
        rec.log("world/sphere/center", rr.Points3D([c], radii=0.03, colors=[palette.SPHERE]), static=True)
        rec.log(
            "world/bbox",
            rr.Boxes3D(
                mins=[e.bbox[0]],
                sizes=[e.bbox[1] - e.bbox[0]],
                colors=[(90, 90, 90)],
                fill_mode="majorwireframe",
                radii=0.003,
            ),
            static=True,
        )
        # The mirror plane used: a translucent square with its normal; the true plane: an outline. A plane
        # that training refines (--refine-plane) moves: its transform is logged at step 0 here and at every step.
        self._plane_size, self._moving_planes = 0.6 * r, set()
        self._plane_moves = e.plane is not None and e.cfg.flip.refine_plane
        if self._plane_moves:
            rec.set_time(STEP, sequence=0)
        if e.plane is not None:
            self._log_plane(
                "world/mirror_plane", e.plane, palette.MIRROR_PLANE, filled=True, static=not self._plane_moves
            )
        if e.true_plane is not None:
            self._log_plane("world/true_plane", e.true_plane, palette.TRUE_PLANE, filled=False, static=True)
        self._frustum_scale = 0.12 * r
        for info, path in zip(e.cameras, camera_paths(e.cameras)):
            self._log_camera(path, info.camera, COLORS[info.kind], info.image)
            if info.kind == "test" and info.image is not None:
                self._log_gt(f"views/test/{entity_name(info.camera.name)}/gt", info.image)
            if info.kind == "mirror_init" and info.image is not None:
                self._log_gt(f"views/mirror/{entity_name(info.camera.name)}/flipped", info.image)
        # The refined mirrored cameras start at the initial mirrored poses (step 0).
        inits = [i for i in e.cameras if i.kind == "mirror_init"] if self._mirror_names else []
        rec.set_time(STEP, sequence=0)
        for info in inits:
            path = f"world/cameras/mirror/{entity_name(info.camera.name)}"
            self._log_camera(path, info.camera, COLORS["mirror"], info.image, pose_static=False)
        self._prev_centers = np.stack([i.camera.center for i in inits]) if inits else None
        if inits:
            for q in ("rot_change_deg", "trans_change", "rot_err_deg", "trans_err"):
                rec.log(
                    f"curves/mirror/{q}",
                    rr.SeriesLines(names=self._mirror_names, colors=self._series_colors),
                    static=True,
                )
        settings = "\n".join(f"- **{k}**: {v}" for k, v in e.cfg.to_dict().items())
        rec.log(
            "run",
            rr.TextDocument(
                f"# {e.run_name}\n\nscene **{e.scene}**, method **{e.method}**, {split_label(e.config)}, "
                f"{e.total_steps} steps\n\n{settings}",
                media_type="text/markdown",
            ),
            static=True,
        )

    def _log_plane(self, path: str, plane: Plane, color: tuple[int, int, int], filled: bool, static: bool) -> None:
        """A plane: its square (translucent when `filled`), outline and normal. One that training moves is drawn
        once in its own frame (z = 0, normal +z) and moved by a transform per step: the scene view shows all
        data up to the cursor (for the trajectories), so a square per step stacked into opaque slabs, while a
        transform is read at the cursor alone."""
        if static:
            return self._plane_shape(path, plane, color, filled)
        if path not in self._moving_planes:
            self._plane_shape(path, Plane(np.zeros(3), np.array([0.0, 0.0, 1.0])), color, filled)
            self._moving_planes.add(path)
        self.rec.log(path, rr.Transform3D(translation=plane.point, mat3x3=plane.basis()))

    def _plane_shape(self, path: str, plane: Plane, color: tuple[int, int, int], filled: bool) -> None:
        quad, rec = plane.square(self._plane_size), self.rec
        if filled:
            rec.log(
                path,
                rr.Mesh3D(vertex_positions=quad, triangle_indices=[[0, 1, 2], [0, 2, 3]], albedo_factor=(*color, 60)),
                static=True,
            )
        rec.log(
            f"{path}/outline", rr.LineStrips3D([np.vstack([quad, quad[:1]])], colors=[color], radii=0.006), static=True
        )
        arrow = rr.Arrows3D(
            origins=[plane.point], vectors=[0.67 * self._plane_size * plane.normal], colors=[color], radii=0.012
        )
        rec.log(f"{path}/normal", arrow, static=True)

    def _log_camera(
        self, path: str, cam: Camera, color: tuple[int, int, int], image: np.ndarray | None, pose_static: bool = True
    ) -> None:
        rec = self.rec
        rec.log(path, rr.Transform3D(translation=cam.c2w[:3, 3], mat3x3=cam.c2w[:3, :3]), static=pose_static)
        rec.log(path, rr.TransformAxes3D(axis_length=0.0), static=True)  # frustums only, no axis triads
        rec.log(
            path,
            rr.Pinhole(
                image_from_camera=cam.K,
                resolution=[cam.width, cam.height],
                camera_xyz=rr.ViewCoordinates.RUB,  # flipviz cameras are OpenGL: x right, y up, looking along -z
                image_plane_distance=self._frustum_scale,
                color=color,
                line_width=0.003,
            ),
            static=True,
        )
        if image is not None:
            rec.log(path, self._jpeg(image), static=True)

    def _log_gt(self, path: str, image: np.ndarray) -> None:
        if path not in self._logged_gt:
            self.rec.log(path, self._jpeg(image), static=True)
            self._logged_gt.add(path)

    def on_step(self, event: StepEvent) -> None:
        with self._lock:
            if self._silent:
                return
            self._n_step_events += 1
            if (self._n_step_events - 1) % self.opts.step_stride and event.step != event.total_steps:
                return
            rec = self.rec
            rec.set_time(STEP, sequence=event.step)
            for k, v in event.scalars.items():
                group = "lr" if k.startswith("lr") else "agreement" if k in AGREEMENT_SCALARS else "train"
                self._scalar(f"curves/{group}/{entity_name(k)}", event.step, v)
            if event.mirror_c2w is not None and self._mirror_names:
                self._log_mirrors(event)
            if event.plane is not None and self._plane_moves:
                self._log_plane("world/mirror_plane", event.plane, palette.MIRROR_PLANE, filled=True, static=False)
                for k in ("plane_err_deg", "plane_err_offset"):
                    if getattr(event, k) is not None:
                        self._scalar(f"curves/plane/{k.removeprefix('plane_')}", event.step, getattr(event, k))
            self._maybe_flush()

    def _log_mirrors(self, e: StepEvent) -> None:
        rec = self.rec
        c2w = np.asarray(e.mirror_c2w, dtype=np.float64)
        for name, T in zip(self._mirror_names, c2w):  # sent as columns with the curves (`_hold`)
            self._hold(self._poses, f"world/cameras/mirror/{name}", e.step, T.copy())
        centers = c2w[:, :3, 3]
        if self._prev_centers is not None and len(self._prev_centers) == len(centers):
            # One new segment per camera per step: the file grows linearly with the steps.
            strips = np.stack([self._prev_centers, centers], axis=1)
            rec.log("world/trajectories", rr.LineStrips3D(strips, colors=[COLORS["mirror"]], radii=0.004))
        self._prev_centers = centers
        for q in ("rot_change_deg", "trans_change", "rot_err_deg", "trans_err"):
            v = getattr(e, f"mirror_{q}")
            if v is not None:
                self._scalar(f"curves/mirror/{q}", e.step, v)
        if e.mirror_ratio is not None:  # each mirror's own disagreement (training/flip.py: Agreement)
            self._scalar("curves/agreement/per_mirror", e.step, e.mirror_ratio)
        for i, at in enumerate(e.mirror_dropped_at or ()):
            if at is not None and i not in self._dropped:
                self._dropped.add(i)
                name = self._mirror_names[i] if i < len(self._mirror_names) else str(i)
                self.rec.log("log", rr.TextLog(f"mirrored view {name} dropped at step {at}", level="WARN"))

    def on_images(self, event: ImagesEvent) -> None:
        with self._lock:
            if self._silent:
                return
            rec = self.rec
            rec.set_time(STEP, sequence=event.step)
            for k, v in event.scalars.items():
                rec.log(f"curves/test/{entity_name(k)}", rr.Scalars(float(v)))
            for v in event.test_views:
                self._log_view(f"views/test/{entity_name(v.name)}", v, gt_name="gt")
            for v in event.mirror_views:
                self._log_view(f"views/mirror/{entity_name(v.name)}", v, gt_name="flipped")
            self._n_images += 1
            if self.opts.splats_every > 0 and self._n_images % self.opts.splats_every == 0:
                self._log_splats(event.step)
            self._maybe_flush(force=True)

    def _log_splats(self, step: int) -> None:
        """The field's solid cells as Gaussian splats (splats.py): the 3D model in the recording. One
        scale for all (Rerun repeats a single value over the instances): 16 bytes a splat."""
        baked = self._bake() if self._bake is not None and step != self._splats_step else None
        if baked is None:
            return
        self._splats_step = step
        s = solid_splats(baked)
        rgba = np.concatenate([s.rgbs, np.round(255.0 * s.opacities).astype(np.uint8)[:, None]], 1)
        self.rec.log("world/field", rr.GaussianSplats3D(s.centers, scales=[[s.sigma] * 3], colors=rgba))

    def _log_view(self, base: str, v: RenderedView, gt_name: str) -> None:
        rec = self.rec
        rec.log(f"{base}/render", self._jpeg(v.rgb))
        near, far = self._depth_range
        rec.log(f"{base}/depth", self._map(v.depth, palette.SCALAR_CMAP, near, far))
        rec.log(f"{base}/opacity", self._map(v.opacity, palette.SCALAR_CMAP, 0.0, 1.0))
        if v.gt is not None:
            self._log_gt(f"{base}/{gt_name}", v.gt)
            err = np.abs(np.asarray(v.rgb, np.float32) - np.asarray(v.gt, np.float32)).mean(-1)
            rec.log(f"{base}/error", self._map(err, palette.SCALAR_CMAP, 0.0, self.opts.error_max))
        if v.beta2 is not None:
            rec.log(f"{base}/beta2", self._map(v.beta2, palette.SCALAR_CMAP, *self.opts.beta2_range))

    def on_end(self, event: EndEvent) -> None:
        with self._lock:
            if self._silent:
                return
            rec = self.rec
            rec.set_time(STEP, sequence=event.step)
            rec.log(
                "log",
                rr.TextLog(
                    f"run {event.status} at step {event.step}. {event.message}".strip(),
                    level="ERROR" if event.status in ("nan", "error") else "INFO",
                ),
            )
            for k, v in event.metrics.items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    rec.log(f"curves/final/{entity_name(k)}", rr.Scalars(float(v)))
            if self.opts.splats_every > 0 and event.status in ("finished", "stopped"):
                self._log_splats(event.step)  # the model as it ended (unless the last images logged it)
            self._maybe_flush(force=True)
            # Finalise the file (footer). A served viewer keeps what it received until close().
            rec.disconnect()
            if self.opts.path is not None and self.opts.optimize:
                optimize_recording(self.opts.path)
            if self.viewer is not None:
                print(f"Rerun web viewer (run {event.status}): {self.viewer.url}", flush=True)

    def close(self) -> None:
        """Finalise the recording and stop the local web viewer, if one was started."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self._sinks_ready and self.opts.path is not None:  # stopped in setup (e.g. the plane estimate)
                self.rec.set_sinks(rr.FileSink(str(self.opts.path)))  # still a readable recording, not an empty file
                self.rec.log("log", rr.TextLog("the run stopped during its setup, before training began", level="WARN"))
            if not self._silent:
                self._send_columns()
            self.rec.flush(timeout_sec=5.0)
            self.rec.disconnect()
        except Exception:
            pass
        if self.viewer is not None:
            self.viewer.stop()

    @property
    def viewer_url(self) -> str | None:
        return self.viewer.url if self.viewer is not None else None


def optimize_recording(path: Path, timeout_s: float = 300.0) -> bool:
    """Compact a finished recording in place with Rerun's own `rerun rrd optimize`. A run logs a small
    chunk per step and entity, and a viewer opens many small chunks slowly. The compacted copy replaces
    the file only once it is written whole; on any failure the original stays (one log line). True
    when replaced."""
    tmp = path.with_name(path.name + ".optimizing")
    try:
        subprocess.run(
            [sys.executable, "-m", "rerun_cli", "rrd", "optimize", str(path), "-o", str(tmp)],
            check=True,
            capture_output=True,
            timeout=timeout_s,
        )
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise RuntimeError("it wrote nothing")
        with signals_deferred():  # the recording is either the old file or the whole new one
            os.replace(tmp, path)
        return True
    except (OSError, RuntimeError, subprocess.SubprocessError) as e:
        log.warning(
            "recording %s kept as written (not compacted: %s)",
            path,
            str(e).splitlines()[0] if str(e) else type(e).__name__,
        )
        tmp.unlink(missing_ok=True)
        return False


FOOTER_MAGIC = b"RRF2FOOT"  # a finalised .rrd ends with its footer (the manifest of its chunks), this, a version


def has_footer(path: Path) -> bool:
    """The recording was finalised (`disconnect`, the end of a run). A writer that was killed (SIGKILL, a
    power cut) stops before its footer: every chunk up to its last flush reads (`RrdReader`, the
    viewer, `rerun rrd verify --check-footers false`), but `rerun rrd verify` reports the footer missing."""
    with open(path, "rb") as f:
        f.seek(max(0, path.stat().st_size - 4 * len(FOOTER_MAGIC)))
        return FOOTER_MAGIC in f.read()


def finalise_killed_recordings(run_dir: Path) -> list[Path]:
    """Give the recordings of a killed run in `run_dir` their footer (`optimize_recording` writes the
    chunks anew, whole, with one), when a run takes the folder over again (--resume): afterwards
    `rerun rrd verify` passes on every recording of the folder. Returns those finalised."""
    done = []
    for path in sorted(Path(run_dir).glob("recording*.rrd")):
        if path.is_file() and path.stat().st_size > 0 and not has_footer(path) and optimize_recording(path):
            log.info("finalised %s, which a killed run left without its footer", path)
            done.append(path)
    return done


def recording_path(cfg: TrainConfig, run_dir: Path) -> Path | None:
    """Where a run records: cfg.output.rrd, else <run_dir>/recording.rrd. An earlier recording is never
    replaced: the run writes the next free recording.N.rrd beside it (a resumed run's recordings
    open together: `rerun <run folder>/*.rrd`; --overwrite deletes the earlier run's first).
    A path that cannot be written is a one-line UserError (the Trainer refused one in the folder of
    another run in training: artifacts.refuse_to_overwrite)."""
    if cfg.output.no_rrd:
        return None
    path = Path(cfg.output.rrd) if cfg.output.rrd is not None else Path(run_dir) / "recording.rrd"
    check_recording_target(path)
    path = next_free(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab"):
            pass
    except OSError as e:
        raise UserError(f"cannot write the recording {path}: {e.strerror or e}") from None
    return path


def make_rerun_observer(
    cfg: TrainConfig, run_dir: Path, bake: Callable[[], dict] | None = None, **overrides
) -> RerunObserver:
    """The observer the CLI and the app attach (see `recording_path`; cfg.output.rerun_serve); `bake`: the
    trainer's `point_cloud`, for the field's splats."""
    finalise_killed_recordings(run_dir)  # a killed part of this run (it is resumed) ends readable and verified
    return RerunObserver(
        RerunOptions(path=recording_path(cfg, run_dir), serve=cfg.output.rerun_serve, **overrides), bake
    )
