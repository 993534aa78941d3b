"""The browser app: train a run in the background and watch / probe it with viser.

`run_app(cfg)` serves viser on cfg.host:cfg.port and trains with the real `Trainer` in a
background thread (viz/app/session.py: start, restart, stop; recording Rerun unless
--no-rrd). The app observes the trainer through `RunEvents` (viz/run_events.py): events are copied
in the trainer's thread and drawn by a UI thread a few times a second; it acts on training only
through the trainer's public methods (render, point_cloud, pause, resume, stop).
All renders go through one duty-cycled `RenderWorker`, so browsers never stall training for long.

The app is the `RunView` (viz/run_view.py) its panels read. Panels: viser_train (the Train tab),
viser_render (each browser's own view), viser_preview (the live 3D preview), viser_novel (novel
cameras, snap to view), viser_mirror (the symmetry lesson), viser_compare (A/B with a second run,
camera paths), viser_scene (the run's 3D scene).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
import warnings
import webbrowser
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import viser

from flipviz.data import SceneData, TooWide, load_scene
from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane
from flipviz.data.protocol import N_OBSERVED, TURN
from flipviz.errors import UserError
from flipviz.files import inside_roots, signals_deferred
from flipviz.geometry.mirror import make_mirror_set
from flipviz.geometry.symmetry import PlaneEstimate
from flipviz.options import Range
from flipviz.training.config import DataConfig, EngineConfig, FlatFlags, TrainConfig, with_preset
from flipviz.training.events import SetupEvent, StepEvent
from flipviz.training.plane_estimate import estimate_plane
from flipviz.training.setup import run_split
from flipviz.viz import palette
from flipviz.viz.app.compare import ComparePanel
from flipviz.viz.app.gui_thread import on_gui_thread, thread_safe_pushes
from flipviz.viz.app.mirror.tab import MirrorLesson
from flipviz.viz.app.novel import NovelCameras, SnapToView
from flipviz.viz.app.poses import plane_to_arg
from flipviz.viz.app.preview import LivePreview
from flipviz.viz.app.probe import PixelProbe
from flipviz.viz.app.render import RenderWorker, ViewportRenderer
from flipviz.viz.app.scene import GROUPS, RunScene
from flipviz.viz.app.session import TrainingSession
from flipviz.viz.app.train import TUNED_VIEW_S, RunChoice, TrainPanel, fmt_time, run_choice, scoring_settings, scorings
from flipviz.viz.run_events import RunEvents

log = logging.getLogger("flipviz.app")


class OneLineErrors(logging.Filter):
    """A client's malformed websocket message is one log line, not a traceback: undecodable bytes
    close its connection (websockets' handler logs them), a message of the wrong shape fails in
    viser's handler task (asyncio logs "Task exception was never retrieved")."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            e = record.exc_info[1]
            first = lambda text: (text.splitlines() or [""])[0]  # noqa: E731
            record.msg, record.args = f"{first(record.getMessage())}: {type(e).__name__}: {first(str(e))}", ()
            record.exc_info, record.exc_text = None, None
        return True


for _name in ("websockets.server", "asyncio"):
    logging.getLogger(_name).addFilter(OneLineErrors())
# a client's value of the wrong type; a render for a client that just left
warnings.filterwarnings("ignore", message=r"\[viser\] .* does not match annotation")
warnings.filterwarnings("ignore", message=r"Queued a \w+ on a closed connection")


@dataclass
class AppConfig(TrainConfig):
    """A training run plus the browser app that shows it (`python app.py --scene chair`)."""

    # --res 200, twice `flipviz train`'s 100 px (narrower data, a 100 px capture, trains at its own
    # width): over the app's 3000 steps, training at 200 px scored +2.5 dB (Upper) and +0.8 dB (B/L) at
    # 200 px on held-out views of the chair that the protocol never uses, in the same training time (the
    # grid stays 64^3 -> 128^3; docs/results/resolution). At 600 steps it bought nothing consistent
    # (-0.2 to +0.4 dB).
    data: FlatFlags[DataConfig] = field(default_factory=lambda: DataConfig(res=200))
    # --steps 3000, more than `flipviz train`'s 600, so that a newcomer watches training happen (about
    # 2-3 minutes on 2 cores); the Train tab restarts with any other count.
    engine: FlatFlags[EngineConfig] = field(default_factory=lambda: EngineConfig(steps=3000))
    port: Annotated[int, Range(0, 65535)] = 8080
    """Port of the web app (the next free one is used when it is busy; 0: any free port)."""
    host: str = "127.0.0.1"
    """Address to bind; 127.0.0.1 keeps the app local to this machine."""
    open_browser: bool = False
    """Open the app in the default web browser."""
    view_width: Annotated[int, Range(128, 1920)] = 800
    """Default "max resolution" (pixels, width, 128..1920) of the render of your own still view."""
    render_duty: Annotated[float, Range(0.01, 1.0)] = 0.25
    """At most this fraction (0.01..1) of wall time goes to browser renders (they share the trainer's lock)."""
    restart_checkpoints_mb: Annotated[float, Range(0.0, 1e7)] = 500.0
    """Disk budget for the checkpoints of runs an in-app restart replaced (tens of MB each): the newest
    are kept, so Compare can load them as run B; older ones are deleted (their metrics, renders and
    recordings stay). 0 deletes each when it is replaced."""
    browse_root: tuple[Path, ...] = ()
    """Folders a browser may open runs (Compare) and data (Restart) from, besides runs/, the folder
    beside this app's run folders and --data. Anything else typed in the browser is refused."""


def check_host(host: str, port: int) -> None:
    """The address can be served on (viser moves on to the next free port, but not to another host)."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise UserError(f"--host {host!r} is not an address of this machine ({e.strerror})") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        try:
            s.bind((addr[0], 0))  # any port: only the host is checked here
        except OSError as e:
            raise UserError(f"cannot serve on --host {host!r}: {e.strerror}") from None


def check_run_input(cfg: AppConfig) -> tuple[AppConfig, SceneData]:
    """Check the settings, load the scene and build its mirror plane, and check a --resume checkpoint,
    all before serving: bad input fails in one line, at once. Data narrower than --res (the app's 200
    px over a 100 px capture) trains at its own width: the settings come back with that --res."""
    from flipviz.training.artifacts import check_named_files, refuse_to_overwrite

    cfg.validate()
    check_host(cfg.host, cfg.port)
    check_named_files(cfg)
    if cfg.output.out is not None:
        refuse_to_overwrite(Path(cfg.output.out), cfg)
    try:
        scene = load_scene(cfg.data.scene, cfg.data.path, cfg.data.res)
    except TooWide as e:
        log.warning("%s: the app trains at the images' own %d px", e, e.width)
        cfg = cfg.with_settings(res=e.width)
        scene = load_scene(cfg.data.scene, cfg.data.path, cfg.data.res)
    inputs = run_split(cfg, scene).inputs
    if cfg.flip.mirror_plane != "auto":  # auto is estimated when the run starts
        make_mirror_set(
            inputs, cfg.flip.mirror_plane, scene.symmetry_plane, scene.center, scene.up, pose=cfg.flip.mirror_pose
        )
    return cfg, scene


class App:
    """Viser server + background trainer + GUI. Start with `start()`, end with `stop()`."""

    def __init__(self, cfg: AppConfig, scene: SceneData | None = None) -> None:
        self._first = cfg  # the command line's settings (browse roots); the session's cfg follows restarts
        self.events = RunEvents()  # what the trainer's thread hands the UI thread
        self.session = TrainingSession(cfg, [self.events], scene, checkpoints_mb=cfg.restart_checkpoints_mb)
        thread_safe_pushes()  # the render worker, callbacks and the UI tick all write to the browsers
        self.server = viser.ViserServer(host=cfg.host, port=cfg.port, label="flipviz", verbose=False)
        self._set_initial_camera(np.zeros(3), 4.0)
        self.port = self.server.get_port()  # the port actually bound (viser moves on when it is busy)
        shown = "localhost" if cfg.host in ("0.0.0.0", "::", "") else cfg.host
        self.url = f"http://{shown}:{self.port}"
        self.worker = RenderWorker(cfg.render_duty)
        self.scene = RunScene(self.server)
        self.setup: SetupEvent | None = None  # the run the browsers show (built by the UI thread)
        self._closing = threading.Event()
        self._ui_thread = threading.Thread(target=self._ui_loop, name="flipviz-ui", daemon=True)
        self._build_gui()
        self.views = ViewportRenderer(self.worker, self, self.preview, self.compare, self._on_unsnap, cfg.view_width)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

    # ---- GUI --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=palette.CAMERA["mirror"])
        gui.main_panel.dock_right()  # beside the 3D view, not over it: the whole canvas is seen (side by side's B)
        tabs = gui.add_tab_group()
        with tabs.add_tab("Train", viser.Icon.PLAYER_PLAY) as train_tab:
            choices = scorings(self._first.eval)  # flipviz's, the authors', and the command line's own
            self.train = TrainPanel(self.server, self.pause, self.resume, self.restart_with, train_tab, choices)
            self.your_view = gui.add_folder("Your view")
        with tabs.add_tab("Views", viser.Icon.CAMERA):
            with gui.add_folder("Snap to view"):
                self.snap = SnapToView(self.server, self.worker, self, self._snap_client)
                self.probe = PixelProbe(self.server, self.worker, self, after=self.snap.text)
            with gui.add_folder("Novel cameras"):
                self.novel = NovelCameras(self.server, self.worker, self)
        with tabs.add_tab("Mirror", viser.Icon.FLIP_VERTICAL):
            self.mirror = MirrorLesson(self.server, self.worker, self, self.scene, self.restart_with_plane)
        with tabs.add_tab("Compare", viser.Icon.LAYOUT_COLUMNS):
            self.compare = ComparePanel(
                self.server,
                self,
                self.session,
                self.browse_roots,
                on_change=lambda: self.views.request_all(),
                on_shown=self._compare_shown,
            )
        with tabs.add_tab("Show", viser.Icon.EYE):
            gui.add_image(palette.legend_image(), label="Colours", format="png")
            with gui.add_folder("3D preview"):
                self.preview = LivePreview(self.server, self.worker, self)
            with gui.add_folder("Scene"):
                self.group_boxes = {
                    g: gui.add_checkbox(label, self.scene.visible[g]) for g, (label, _) in GROUPS.items()
                }
                for g, cb in self.group_boxes.items():
                    cb.on_update(lambda ev, g=g: self.scene.set_visible(g, ev.target.value))
        self._hidden_for_compare: list[viser.GuiCheckboxHandle] = []
        self.server.scene.on_click()(self._on_click)

    def _on_click(self, ev: viser.SceneClickEvent) -> None:
        """A click in a browser's 3D view probes the pixel under it, when that browser is at a snapped view."""
        view = self.views.clients.get(ev.client_id)
        snapped = view.snapped if view is not None else None
        self.probe.click(
            snapped if snapped is not None and self.views.at(view, snapped.camera) else None,
            np.asarray(ev.ray_direction),
        )

    def _on_unsnap(self) -> None:
        """A browser's camera left its snapped view: what was hidden comes back, the Views panel's images go."""
        self.scene.unhide()
        self.mirror.set_snapped(False)
        self.snap.clear()
        self.probe.clear()

    def _compare_shown(self, shown: bool) -> None:
        """While Compare draws the views, the translucent plane squares are turned off (they would wash
        over both runs); they come back when it stops. The user may turn them on meanwhile."""
        if shown:
            boxes = (self.mirror.show_plane, self.group_boxes["true_plane"])
            self._hidden_for_compare = [cb for cb in boxes if cb.value]
            for cb in self._hidden_for_compare:
                cb.value = False
        else:
            for cb in self._hidden_for_compare:
                cb.value = True
            self._hidden_for_compare = []

    def _set_initial_camera(self, center: np.ndarray, radius: float) -> None:
        """New tabs start outside the camera sphere, above the camera ring, looking at its centre (z up)."""
        cam = self.server.initial_camera
        cam.position = center + radius * np.array([1.0, -1.0, 1.9])
        cam.look_at = center
        cam.fov = np.deg2rad(50.0)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        try:
            self.views.add_client(client, folder=self.your_view)
            self.preview.set_visible(client.client_id, True)
        except RuntimeError as e:  # the client left while its panel was built: viser removed its handles
            log.info("a client left while it connected (%s)", str(e).splitlines()[0])
            self._on_disconnect(client)

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        self.views.remove_client(client.client_id)
        self.preview.remove_client(client.client_id)

    def _snap_client(self, client: viser.ClientHandle, cam: Camera, reference: np.ndarray | None, name: str) -> None:
        from flipviz.viz.app.render import Snapped

        self.scene.hide_near(cam.center, 0.35 * float(self.setup.sphere_radius) if self.setup else 1.0)
        self.mirror.set_snapped(True)
        self.probe.clear()  # its reading and marker belong to the view left (the dot would sit on the object)
        self.views.snap(client.client_id, Snapped(cam, reference, name))

    # ---- the run: viz/app/session.py owns its lifecycle ----------------------------------
    @property
    def cfg(self) -> AppConfig:
        return self.session.cfg

    @property
    def trainer(self):
        return self.session.trainer

    @property
    def status(self) -> str:
        return self.session.status

    @property
    def message(self) -> str:
        return self.session.message

    @property
    def restarts(self) -> int:
        return self.session.restarts

    @property
    def run_dirs(self) -> list[Path]:
        return self.session.run_dirs

    def browse_roots(self) -> list[Path]:
        """The folders a browser may name (AppConfig.browse_root): all were given on the command line."""
        roots = {Path("runs"), *(d.parent for d in self.run_dirs), *self._first.browse_root}
        if self._first.output.out is not None:
            roots.add(Path(self._first.output.out).parent)
        if self._first.data.path is not None:
            roots.add(Path(self._first.data.path))
        return sorted(roots)

    @property
    def training(self) -> bool:
        return self.status == "running"

    @property
    def step(self) -> int:
        return self.events.step

    @property
    def mirror_c2w(self) -> np.ndarray | None:
        return self.events.mirror_c2w

    def point_cloud(self) -> dict | None:
        trainer = self.trainer
        return trainer.point_cloud() if trainer is not None else None

    # ---- training control -------------------------------------------------------------------
    def start(self) -> App:
        self._ui_thread.start()
        self.session.start()
        return self

    def pause(self) -> None:
        if self.session.pause():
            self.train.set_controls(self.status)

    def resume(self) -> None:
        if self.session.resume():
            self.train.set_controls(self.status)
            self.preview.request()

    def building(self) -> bool:
        """A trainer is still being built (scene loading, ray casting) in the training thread."""
        return self.session.building()

    def restart_with(self, choice: RunChoice, client: viser.ClientHandle | None = None) -> None:
        """Restart with the Train tab's choice of scene (or data folder), method, configuration, steps;
        `client` (the browser that asked) is asked first when a run would be replaced or the setting is
        sized for another device."""
        try:
            data = inside_roots(choice.data, self.browse_roots(), "data folder") if choice.data else None
        except UserError as e:  # a folder the command line did not name: refused, the run goes on
            self.train.say(f"**Not restarted:** {e}")
            return
        scene = choice.scene if choice.scene is not None else self.cfg.data.scene
        cfg = with_preset(self.cfg, choice.preset).with_settings(
            scene=scene,
            data=data,
            method=choice.method,
            config=choice.config,
            steps=choice.steps,
            **scoring_settings(choice, self.train.scorings),
        )
        question = self.restart_question(cfg)
        if client is None or question is None:
            self.restart(cfg)
        else:
            self.train.ask(client, question, lambda: self.restart(cfg))

    def restart_question(self, new: AppConfig) -> str | None:
        """What to know before `new` replaces the run (None: nothing is lost, nothing is slow)."""
        lines, trainer = [], self.trainer
        if trainer is not None and self.step > 0:
            run_dir = trainer.run_dir
            lines.append(
                f"**Replace this run** ({self.cfg.data.scene}, {self.cfg.method}, step {self.step} of "
                f"{trainer.total_steps})? "
                f"Its checkpoint, metrics and recording stay in `{run_dir}`: *Compare with the previous run* "
                "(Compare tab) brings it back beside the new one."
            )
        rate = self.train.pace.rate()
        same_speed = (new.preset, new.engine.field, new.data.res) == (
            self.cfg.preset,
            self.cfg.engine.field,
            self.cfg.data.res,
        )
        if rate and same_speed:
            eta = fmt_time(new.engine.steps / rate)
            lines.append(f"The new run: {new.engine.steps} steps, about {eta} at this run's pace.")
        if new.preset == "paper" and not new.engine.device.startswith("cuda"):
            lines.append(
                f"**The paper setting is sized for a GPU** ({new.engine.field} field, {new.engine.n_samples} samples "
                f"per ray, {new.engine.steps} steps), and this app runs on `{new.engine.device}`: its steps and each "
                "evaluation of its views take minutes here (20 steps and their evaluation took 28 min on 2 cores)."
            )
        if new.eval.eval_tune_steps > 0:  # issue 40: the authors' scoring, labelled and costed before it starts
            n = len(range(0, TURN - N_OBSERVED, new.eval.eval_every))  # a built-in's first turn less its inputs
            cost = "" if new.data.path else f" ({n} views on a built-in scene: about {fmt_time(n * TUNED_VIEW_S)})"
            lines.append(
                f"**Scored in {new.eval.words()}** when it ends: it looks at the test images, as the released code "
                f"does. About {TUNED_VIEW_S:.0f} s a view at 200 px on 2 cores{cost}."
            )
        return "\n\n".join(lines) if lines else None

    def restart_with_plane(self, plane: Plane) -> None:
        """Retrain with `plane` as the mirror plane (with Flip+U unless a Flip method is running)."""
        method = self.cfg.method if self.cfg.method in ("flip", "flip+u") else "flip+u"
        self.restart(self.cfg.with_settings(mirror_plane=plane_to_arg(plane), method=method))

    def restart(self, cfg: AppConfig) -> None:
        """Stop the current run and train `cfg` from scratch in a new run folder (TrainingSession.restart),
        the views cleared in between."""
        if self._closing.is_set():
            return
        self.train.set_controls("restarting")
        self.session.restart(cfg, on_stopped=self._clear_run)

    def _clear_run(self) -> None:
        """Forget the stopped run: its renders, 3D scene, panels and buffered events."""
        self.worker.cancel(lambda k: True)
        self.scene.clear()
        self.mirror.clear()
        self.preview.clear()
        self.novel.reset()
        self.probe.clear()
        self.compare.clear()
        self.events.clear()
        self.setup = None

    def stop(self) -> None:
        """Stop training (joined: checkpoint and recording flushed), the renders and the server."""
        self._closing.set()
        self.session.stop()
        self.compare.stop()
        self.worker.stop()
        if self._ui_thread.is_alive():
            self._ui_thread.join(timeout=5.0)
        self.server.stop()

    def render(self, camera: Camera, outputs=("rgb", "depth", "opacity", "beta2")) -> dict | None:
        """Thread-safe render of the current model (None while no model exists)."""
        trainer = self.trainer
        if trainer is None:
            return None
        return trainer.render(camera, outputs=outputs)

    def estimate_plane(self) -> PlaneEstimate | None:
        """The mirror plane estimated from the current run's inputs alone (None while no run exists): the run's
        own when it used auto, else estimated now (10-20 s on 2 cores; the training is not touched)."""
        trainer = self.trainer
        if trainer is None:
            return None
        if trainer.plane_estimate is not None:
            return trainer.plane_estimate
        return estimate_plane(trainer.split.inputs, trainer.scene, trainer.cfg.engine.device, trainer.cfg.engine.seed)

    # ---- UI thread --------------------------------------------------------------------------
    def _ui_loop(self, period: float = 0.25) -> None:
        """Four times a second, the browsers catch up with training: on viser's loop thread (gui_thread)."""
        self._last_plot = self._last_mirrors = 0.0
        while not self._closing.wait(period):
            try:
                on_gui_thread(self.server, self._ui_tick, timeout=60.0)
            except Exception:
                log.exception("UI update failed")

    def _ui_tick(self) -> None:
        news = self.events.take()
        if news.setup is not None:
            self.setup = news.setup
            self._new_run(news.setup)
        now = time.monotonic()
        if news.step is not None and now - self._last_mirrors > 0.5 and news.step.mirror_c2w is not None:
            self.scene.update_mirrors(news.step.mirror_c2w)
            self._last_mirrors = now
        if news.step is not None and news.step.mirror_dropped_at is not None:
            self.scene.set_dropped(news.step.mirror_dropped_at)
            self.mirror.on_dropped(news.step.mirror_dropped_at)
        if now - self._last_plot > 1.0:
            with self.events.curves() as curves:
                if curves is not None:
                    self.train.set_plot(curves.psnr_data())
                    self.mirror.curves.show(curves)
            self.compare.show_status()
            self._last_plot = now
        if news.images is not None:
            self.mirror.consistency.on_images(news.images)
        if news.plane is not None:
            self.mirror.follow_training(news.plane)
        self.train.set_controls(self.status)
        self._update_progress(news.step)
        if self.compare.keyframes and self.setup is not None:
            cams = [c.camera.position for c in self.server.get_clients().values()]
            self.compare.hide_keyframes_at(cams, 0.05 * float(self.setup.sphere_radius))

    def _new_run(self, setup: SetupEvent) -> None:
        self._set_initial_camera(np.asarray(setup.sphere_center), float(setup.sphere_radius))
        self.scene.build(setup)
        self.mirror.clear()
        self.mirror.build(setup)
        self.snap.rebuild()
        self.compare.refresh()
        self.compare.follow(setup.cfg)
        self.views.unsnap_all()
        self.train.show_run(run_choice(self.cfg, self.train.scorings))
        self.views.request_all()
        self.preview.request(delay=1.0)

    def _update_progress(self, ev: StepEvent | None) -> None:
        trainer = self.trainer
        run_dir = str(trainer.run_dir) if trainer is not None and self.setup is not None else None
        self.train.show_progress(
            self.setup, self.status, ev, self.events.test_psnr, self.worker.share(), self.message, run_dir
        )


def run_app(cfg: AppConfig) -> None:
    """Serve the app and train until Ctrl-C (training keeps being served after it finishes)."""
    logging.basicConfig(level=logging.WARNING, format="[flipviz] %(message)s")
    cfg, scene = check_run_input(cfg)
    app = App(cfg, scene=scene).start()
    if cfg.port and app.port != cfg.port:
        print(f"[flipviz] port {cfg.port} is busy or not allowed; serving on port {app.port}", flush=True)
    print(f"[flipviz] app running at {app.url}  (Ctrl-C to stop)", flush=True)
    if cfg.open_browser:
        webbrowser.open(app.url)
    stopped_by = signal.SIGINT
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM / SIGHUP raised as one by the CLI
        stopped_by = signal.Signals[str(e)] if str(e) in signal.Signals.__members__ else signal.SIGINT
        print("[flipviz] stopping: saving the checkpoint and the recording...", flush=True)
    finally:
        with signals_deferred():  # a second Ctrl-C waits until the checkpoint and recording are written
            app.stop()
        print("[flipviz] stopped.", flush=True)
        if app.building():  # a trainer still loading its scene has nothing to save: do not wait for it
            sys.stdout.flush(), sys.stderr.flush()
            os._exit(128 + stopped_by)
