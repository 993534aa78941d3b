"""The Compare tab: the current run (A) next to a second run (B) from the same camera, and camera paths.

Run B is a finished run folder (any run with a checkpoint: `runs/`, a bench with --keep-checkpoints,
an earlier run of this app), opened read-only (`training.run.open_run`), or another method trained
next to this one (same scene, views and steps, in its own folder). Every browser's view then shows:

    split           A left of the divider, B right of it (the Divider slider moves it)
    side by side    A | B, each the centre of your view at the full height
    difference      |A - B| on the error colour scale: where the two runs disagree

Moving the camera re-renders both. A snapped view also scores both against its ground truth.
The camera path records your browser's camera as keyframes and renders them (and the ground truth,
|error| and beta^2) to an MP4 in the run's folder, for A alone or A and B together
(flipviz/viz/export/video.py); keyframes.json can be rendered again with `flipviz video RUN --path`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import viser

from flipviz.data.cameras import Camera
from flipviz.data.images import to_uint8
from flipviz.errors import UserError
from flipviz.files import inside_roots, next_free
from flipviz.training.checkpoint import CHECKPOINT_NAME
from flipviz.training.config import METHOD_LABELS, METHODS, TrainConfig, with_preset
from flipviz.training.evaluate import image_psnr
from flipviz.viz import palette
from flipviz.viz.app.guard import bounded, guard_choice, guard_number
from flipviz.viz.app.poses import camera_from_viser, to_viser_pose
from flipviz.viz.app.session import TrainingSession, train_config
from flipviz.viz.app.train import SETTING_HINT, SETTINGS
from flipviz.viz.camera_path import KEYFRAMES_FILE, write_keyframes
from flipviz.viz.images import error_map, view_depth
from flipviz.viz.run_view import RunView

log = logging.getLogger("flipviz.app")

MODES = ("off", "split", "side by side", "difference")
NONE = "(choose a run)"
NO_B = "_No run B yet._"  # the tab's line until a run B is loaded or trained
MAX_FRAMES = 2000  # frames of a camera-path video
MAX_KEYFRAMES = 100


def split_image(a: np.ndarray, b: np.ndarray, x: int, line: bool = True) -> np.ndarray:
    """A's columns left of x, B's from x on (same shapes); a white line between when `line` (uint8 images)."""
    out = np.concatenate([a[:, :x], b[:, x:]], axis=1)
    if line:
        out[:, max(0, x - 1) : min(out.shape[1], x + 1)] = 255
    return out


def label(img: np.ndarray, text: str, x: int = 4, align_right: bool = False) -> np.ndarray:
    """`text` in a white box at the image's top, starting at column x (ending there: align_right), in
    place; sized to the image's width, so that coarse and fine passes show it alike."""
    scale = max(0.3, img.shape[1] / 1400.0)
    thick = max(1, round(1.5 * scale))
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    pad = max(2, round(4 * scale))
    x = int(np.clip(x - tw - 2 * pad if align_right else x, 0, max(0, img.shape[1] - tw - 2 * pad)))
    cv2.rectangle(img, (x, pad), (x + tw + 2 * pad, 3 * pad + th), (255, 255, 255), -1)
    cv2.putText(img, text, (x + pad, 2 * pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, (20, 20, 20), thick, cv2.LINE_AA)
    return img


def run_label(cfg: TrainConfig) -> str:
    """A run's method, and its setting unless it is flipviz's own: "B/L", "B/L (authors)"."""
    return METHOD_LABELS[cfg.method] + ("" if cfg.preset == "fast" else f" ({cfg.preset})")


def views_of(cfg: TrainConfig) -> tuple:
    """What makes two runs' views the same: the scene (or data folder), its inputs and its configuration."""
    d = cfg.data
    return d.scene, str(d.path) if d.path is not None else None, d.inputs, d.config


def finished_runs(folders: list[Path]) -> list[Path]:
    """Run folders holding a checkpoint under `folders` (one level deep, and bench's runs/<key>), newest first."""
    found: set[Path] = set()
    for root in folders:
        if not root.is_dir():
            continue
        for pattern in (CHECKPOINT_NAME, f"*/{CHECKPOINT_NAME}", f"runs/*/{CHECKPOINT_NAME}"):
            found.update(p.parent.resolve() for p in root.glob(pattern))
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


class RunB:
    """The second run: a finished one opened from its folder (saved_run.Run), or a Trainer training in its own
    thread."""

    def __init__(self, trainer, training: bool) -> None:
        self.trainer, self.training = trainer, training
        self.thread: threading.Thread | None = None
        if training:
            self.thread = threading.Thread(target=trainer.run, name="flipviz-train-b", daemon=True)
            self.thread.start()

    @property
    def name(self) -> str:
        return f"{run_label(self.trainer.cfg)} ({self.trainer.run_dir.name})"

    def render(self, camera: Camera, outputs=("rgb", "depth", "opacity")) -> dict:
        return self.trainer.render(camera, outputs)

    def stop(self) -> None:
        if self.thread is not None and self.thread.is_alive():
            self.trainer.stop()
            self.thread.join()


class ComparePanel:
    """GUI of the Compare tab, and the compositor the browsers' views call while it is on."""

    def __init__(
        self,
        server: viser.ViserServer,
        run: RunView,
        session: TrainingSession,
        roots: Callable[[], list[Path]],
        on_change: Callable[[], None],
        on_shown: Callable[[bool], None] = lambda on: None,
    ) -> None:
        """`run`: run A as the views see it; `session`: its settings, folder and the run before it;
        `roots`: the folders a browser may open runs from (B is searched for there)."""
        gui = server.gui
        self.server, self.run, self.session, self.roots = server, run, session, roots
        self.on_change, self.on_shown = on_change, on_shown
        self.shown = False  # whether the views show the comparison (a run B and a mode other than off)
        self.b: RunB | None = None
        self._note = NO_B  # what the tab says while there is no B (loading, or why it failed)
        self._lock = threading.Lock()
        self.scores: dict[str, tuple[float, float]] = {}  # snapped view name -> (PSNR A, PSNR B)
        self._scored_at: dict[str, tuple[int, int]] = {}  # snapped view name -> (A's step, B's step) of its scores
        gui.add_markdown(
            "Compare this run (**A**) with a second run (**B**) from your camera: split, side by side, "
            "or their difference."
        )
        with gui.add_folder("Run B"):
            self.previous_btn = gui.add_button(
                "Compare with the previous run",
                icon=viser.Icon.HISTORY,
                hint="The run this app trained before the current one (its checkpoint is kept)",
            )
            self.runs_dd = gui.add_dropdown(
                "Finished run", (NONE,), hint="Run folders with a checkpoint (runs/, this app's runs)"
            )
            self.refresh_btn = gui.add_button("Find runs", icon=viser.Icon.REFRESH)
            self.path_txt = gui.add_text(
                "Or a folder", "", hint="A run folder with checkpoint.pt, under the app's browse roots"
            )
            self.load_btn = gui.add_button("Load run B", icon=viser.Icon.FOLDER_OPEN)
            self.method_dd = guard_choice(
                gui.add_dropdown("B method", METHODS, initial_value="bl", hint="Train B with this method"), METHODS
            )
            self.setting_dd = guard_choice(gui.add_dropdown("B setting", SETTINGS, hint=SETTING_HINT), SETTINGS)
            self.train_btn = gui.add_button(
                "Train B next to this run",
                icon=viser.Icon.PLAYER_PLAY,
                hint="Same scene, views and steps; both share the CPU",
            )
        self.mode_dd = guard_choice(gui.add_dropdown("Show", MODES, initial_value="off"), MODES)
        self.divider = guard_number(
            gui.add_slider("Divider", 0.0, 1.0, 0.01, 0.5, hint="Split: where A ends and B begins"), 0.0, 1.0
        )
        self.status_md = gui.add_markdown(NO_B)
        with gui.add_folder("Camera path"):
            self.keys_md = gui.add_markdown("No keyframes. Move your camera and add some.")
            self.add_key_btn = gui.add_button("Add keyframe", icon=viser.Icon.CAMERA_PLUS)
            self.clear_keys_btn = gui.add_button("Clear keyframes", icon=viser.Icon.TRASH)
            self.frames_num = guard_number(gui.add_number("Frames", 60, min=2, max=MAX_FRAMES, step=1), 2, MAX_FRAMES)
            self.video_btn = gui.add_button(
                "Render video", icon=viser.Icon.MOVIE, hint="A, and B when loaded; MP4 in A's folder"
            )
            self.video_md = gui.add_markdown("")
        self.keyframes: list[Camera] = []
        self._key_handles: list = []
        self.video_path: Path | None = None
        self.refresh_btn.on_click(lambda _: self.refresh())
        self.load_btn.on_click(lambda _: self._load_chosen())
        self.previous_btn.on_click(lambda _: self._load_previous())
        self.train_btn.on_click(lambda _: self.train_b(self.method_dd.value, self.setting_dd.value))
        self.mode_dd.on_update(lambda _: self._changed())
        self.divider.on_update(lambda _: self.on_change())
        self.add_key_btn.on_click(self._add_key)
        self.clear_keys_btn.on_click(lambda _: self.clear_keyframes())
        self.video_btn.on_click(lambda _: self.render_video())
        self.refresh()

    # ---- run B ----------------------------------------------------------------------------------
    def refresh(self) -> None:
        mine = self.session.run_dir()
        runs = [str(p) for p in finished_runs(self.roots()) if mine is None or p != Path(mine).resolve()]
        self.runs_dd.options = (NONE, *runs)

    def _load_chosen(self) -> None:
        chosen = self.path_txt.value.strip() or (self.runs_dd.value if self.runs_dd.value != NONE else "")
        if not chosen:
            self._say("_Choose a finished run or type a folder first._")
            return
        threading.Thread(target=self.load, args=(Path(chosen),), daemon=True).start()

    def _load_previous(self) -> None:
        folder = self.session.previous_run()
        if folder is None:
            self._say("_No previous run with a checkpoint: restart training once, then compare._")
            return
        threading.Thread(target=self.load, args=(folder,), daemon=True).start()

    def load(self, folder: Path) -> None:
        """Open a finished run as B (a few seconds: its scene and model are loaded). Only a folder under
        the app's browse roots: a browser never makes the server read anywhere else."""
        from flipviz.training.saved_run import open_run

        try:
            folder = inside_roots(folder, self.roots(), "run folder")
        except UserError as e:
            self._say(f"**Cannot load run B:** {e}")
            return
        self._say(f"_Loading `{folder}`..._")
        try:
            trainer = open_run(folder, roots=self.roots())
        except Exception as e:  # a bad folder: one line in the tab, the app goes on
            self._say(f"**Cannot load run B:** {str(e).splitlines()[0]}")
            return
        self._set_b(RunB(trainer, training=False))

    def train_b(self, method: str, preset: str | None = None) -> None:
        """Train `method` as B on this run's scene and views, in A's folder's sibling `<A>-B-<method>`, in
        A's setting or `preset` (e.g. the authors' B/L beside flipviz's: the fog in unseen space)."""
        from flipviz.training.trainer import Trainer

        a_dir, cfg = self.session.run_dir(), train_config(self.session.cfg)
        if a_dir is None:
            self._say("_Run A has not started yet._")
            return
        if preset is not None:
            cfg = with_preset(cfg, preset)
        slug = f"{method.replace('+', 'u')}-{cfg.preset}"  # B's own method and setting, beside A's folder
        out = next_free(f"{a_dir}-B-{slug}")  # beside an earlier run B, never over it
        self._say(f"_Building run B ({method})..._")

        def build() -> None:
            try:
                trainer = Trainer(
                    cfg.with_settings(method=method, out=out, resume=None, no_rrd=True, rrd=None, rerun_serve=False)
                )
            except Exception as e:
                self._say(f"**Cannot train run B:** {str(e).splitlines()[0]}")
                return
            self._set_b(RunB(trainer, training=True))

        threading.Thread(target=build, daemon=True).start()

    def _set_b(self, b: RunB) -> None:
        with self._lock:
            old, self.b = self.b, b
        self._note = NO_B
        if old is not None:
            old.stop()
        self.scores.clear()
        self.show_status()
        if self.mode_dd.value == "off":
            self.mode_dd.value = "split"  # (its callback asks the views again)
        else:
            self._changed()

    def _changed(self) -> None:
        """B or the mode changed: tell the app when the comparison appears or goes, and re-render the views."""
        shown = self.b is not None and self.mode_dd.value != "off"
        if shown != self.shown:
            self.shown = shown
            self.on_shown(shown)
        self.on_change()

    def clear(self) -> None:
        """A new run A is coming: the scores are dropped (B waits for `follow`)."""
        self.scores.clear()
        self.show_status()

    def follow(self, a: TrainConfig) -> None:
        """The new run A's config: B stays when it shows the same views (it may be compared with the new run
        too), and is unloaded when A's scene or views changed (|A - B| would compare two objects)."""
        b = self.b
        if b is None or views_of(b.trainer.cfg) == views_of(a):
            return
        self.stop()
        self._say(
            f"_Run B ({b.name}) was unloaded: it shows **{b.trainer.cfg.data.scene}** configuration "
            f"{b.trainer.cfg.data.config}, the new run A **{a.data.scene}** configuration {a.data.config}. "
            "Load or train a run B of these views to compare._"
        )
        log.info("compare: run B unloaded, run A's views changed")
        if self.mode_dd.value != "off":
            self.mode_dd.value = "off"  # (its callback tells the app the comparison went)
        self._changed()

    def stop(self) -> None:
        with self._lock:
            b, self.b = self.b, None
        if b is not None:
            b.stop()

    def _say(self, note: str) -> None:
        self._note = self.status_md.content = note

    def show_status(self) -> None:
        b = self.b
        if b is None:  # the last note stays until B arrives (the status loop calls this every second)
            if self.status_md.content != self._note:
                self.status_md.content = self._note
            return
        setup = self.run.setup
        lines = [
            f"**B:** {b.name}, step {b.trainer.step}" + (" (training)" if b.training and b.thread.is_alive() else "")
        ]
        if setup is not None and b.trainer.scene.name != setup.scene:
            lines.append(f"B shows **{b.trainer.scene.name}**, A shows **{setup.scene}**: the views differ.")
        for name, (pa, pb) in list(self.scores.items())[-3:]:
            lines.append(f"{name}: PSNR A **{pa:.2f}** dB | B **{pb:.2f}** dB")
        text = "\n\n".join(lines)
        if self.status_md.content != text:
            self.status_md.content = text

    # ---- the browsers' views --------------------------------------------------------------------
    def compose(self, cam: Camera, out_a: dict, snapped) -> tuple[np.ndarray, tuple | None, np.ndarray | None] | None:
        """A view's background, its colour scale and its depth while Compare is on (None: not on, the
        normal view). Called by the render worker with A's render from `cam`; renders B from the same
        camera. The depth is each pixel's own run's where the image is seen from `cam` (split), and none
        where it is not: side by side puts two crops beside each other, a difference has no surface."""
        b = self.b
        if b is None or self.mode_dd.value == "off":
            return None
        mode = self.mode_dd.value
        a_name, b_name = f"A: {run_label(self.session.cfg)}", f"B: {run_label(b.trainer.cfg)}"
        if snapped is not None and snapped.reference is not None:
            self._score(snapped, b)
        if mode == "side by side":
            half = cam.cropped(max(8, cam.width // 2))  # the centre of the view, at its full height and scale
            ra, rb = self.run.render(half, ("rgb",)), b.render(half, ("rgb",))
            if ra is None:
                return None
            img = np.concatenate([label(to_uint8(ra["rgb"]), a_name), label(to_uint8(rb["rgb"]), b_name)], axis=1)
            img[:, half.width - 1 : half.width + 1] = 255
            return img, None, None
        out_b = b.render(cam)
        if mode == "difference":
            return (
                label(error_map(out_a["rgb"], out_b["rgb"]), "|A - B|"),
                (*palette.ERROR_RANGE, "|A - B|, mean over RGB"),
                None,
            )
        x = int(round(bounded(self.divider.value, 0.0, 1.0, 0.5) * cam.width))
        img = split_image(to_uint8(out_a["rgb"]), to_uint8(out_b["rgb"]), x)
        depth = split_image(view_depth(cam, out_a), view_depth(cam, out_b), x, line=False)
        return label(label(img, a_name, x - 4, align_right=True), b_name, x + 4), None, depth

    def _score(self, snapped, b: RunB) -> None:
        """Both runs against the snapped view's ground truth, once per pair of steps (not per render pass)."""
        steps = (self.run.step, b.trainer.step)
        if snapped.name in self.scores and self._scored_at.get(snapped.name) == steps:
            return
        ra = self.run.render(snapped.camera, ("rgb",))
        if ra is None:
            return
        ref = snapped.reference
        self.scores[snapped.name] = (image_psnr(ra["rgb"], ref), image_psnr(b.render(snapped.camera)["rgb"], ref))
        self._scored_at[snapped.name] = steps
        self.show_status()

    # ---- camera path ----------------------------------------------------------------------------
    def _add_key(self, event: viser.GuiEvent) -> None:
        client = event.client
        if client is None:
            return
        cam = client.camera
        self.add_keyframe(
            camera_from_viser(cam.wxyz, cam.position, float(cam.fov), 320, max(8, round(320 / max(cam.aspect, 0.1))))
        )

    def add_keyframe(self, cam: Camera) -> None:
        i = len(self.keyframes)
        if i >= MAX_KEYFRAMES:
            self.keys_md.content = f"_At most {MAX_KEYFRAMES} keyframes: clear them to start another path._"
            return
        self.keyframes.append(cam.with_pose(cam.c2w, name=f"key_{i:03d}"))
        wxyz, pos = to_viser_pose(cam.c2w)
        self._key_handles.append(
            self.server.scene.add_camera_frustum(
                f"/keyframes/{i:03d}",
                fov=cam.fov_y,
                aspect=cam.width / cam.height,
                scale=0.15,
                color=palette.CAMERA["novel"],
                wxyz=wxyz,
                position=pos,
                visible=False,
            )
        )  # shown once no browser's camera sits on it: hide_keyframes_at
        self.keys_md.content = f"**{len(self.keyframes)}** keyframe(s)" + (
            "" if len(self.keyframes) > 1 else ": add one more"
        )

    def hide_keyframes_at(self, positions: list[np.ndarray], radius: float) -> None:
        """A keyframe's frustum where a browser's camera is would frame that whole view in magenta: it is
        hidden while any camera is within `radius` of it (a keyframe is added at your own pose)."""
        for h, key in zip(self._key_handles, self.keyframes):
            show = all(np.linalg.norm(key.center - p) >= radius for p in positions)
            if h.visible != show:
                h.visible = show

    def clear_keyframes(self) -> None:
        for h in self._key_handles:
            h.remove()
        self.keyframes, self._key_handles = [], []
        self.keys_md.content = "No keyframes. Move your camera and add some."

    def render_video(self, res: int = 200) -> threading.Thread | None:
        """Render the keyframe path for A (and B) into A's folder, in a background thread."""
        a_dir, setup = self.session.run_dir(), self.run.setup
        if len(self.keyframes) < 2 or a_dir is None or setup is None:
            self.video_md.content = "_Add two keyframes or more (and wait for the run to start)._"
            return None
        thread = threading.Thread(
            target=self._render_video, args=(Path(a_dir), setup, list(self.keyframes), res), daemon=True
        )
        thread.start()
        return thread

    def _render_video(self, folder: Path, setup, keys: list[Camera], res: int) -> None:
        from flipviz.viz.camera_path import keyframe_path
        from flipviz.viz.export.video import GroundTruth, render_frames, write_mp4

        try:
            write_keyframes(folder / KEYFRAMES_FILE, keys)
            cams = [
                c.resized(res)
                for c in keyframe_path(setup, keys, int(bounded(self.frames_num.value, 2, MAX_FRAMES, 60)))
            ]
            renders = [(f"A: {run_label(self.session.cfg)}", lambda c: self.run.render(c))]
            if self.b is not None:
                b = self.b
                renders.append((f"B: {run_label(b.trainer.cfg)}", b.render))
            done = [0]

            def counted(frames):
                for f in frames:
                    done[0] += 1
                    if done[0] % 5 == 0:
                        self.video_md.content = f"_Rendering frame {done[0]} / {len(cams)}..._"
                    yield f

            scene = self.session.scene()
            gt = GroundTruth(scene) if scene is not None else (lambda c: None)
            path = write_mp4(
                folder / "video_keyframes.mp4", counted(render_frames(renders, cams, gt, progress=False)), 24
            )
            self.video_path = path
            self.video_md.content = f"Wrote `{path}` ({len(cams)} frames); keyframes in `{folder / KEYFRAMES_FILE}`."
        except Exception as e:
            log.warning("camera path video failed: %s: %s", type(e).__name__, e)
            self.video_md.content = f"**Video failed:** {str(e).splitlines()[0]}"
