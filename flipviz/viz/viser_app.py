"""The browser app: train a run in the background and watch / probe it with viser.

`run_app(cfg)` serves viser on cfg.host:cfg.port and trains with the real `Trainer` in a
background thread (recording Rerun unless --no-rrd). The app is an `Observer` of the trainer:
events are copied in the trainer's thread and drawn by a UI thread at a few Hz; it acts on
training only through the trainer's public methods (render, pause, resume, stop). All renders
go through one duty-cycled `RenderWorker`, so browsers never stall training for long.

Modules: viser_scene (3D scene of a run), viser_render (render worker, each client's own view),
viser_novel (novel cameras, snap to view), viser_mirror (the symmetry lesson).
"""

from __future__ import annotations

import logging
import threading
import time
import webbrowser
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import viser

from flipviz.data import SceneData, load_scene
from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane
from flipviz.data.protocol import make_split
from flipviz.geometry.mirror import make_mirror_set
from flipviz.training.config import METHODS, TrainConfig
from flipviz.training.events import EndEvent, ImagesEvent, Observer, SetupEvent, StepEvent
from flipviz.viz.viser_common import plane_to_arg
from flipviz.viz.viser_mirror import MirrorLesson
from flipviz.viz.viser_novel import NovelCameras, SnapToView
from flipviz.viz.viser_render import RenderWorker, ViewportRenderer
from flipviz.viz.viser_scene import GROUPS, RunScene

log = logging.getLogger("flipviz.app")


@dataclass
class AppConfig(TrainConfig):
    """A training run plus the browser app that shows it (`python app.py --scene chair`)."""

    port: int = 8080
    """Port of the web app (the next free one is used when it is busy)."""
    host: str = "127.0.0.1"
    """Address to bind; 127.0.0.1 keeps the app local to this machine."""
    open_browser: bool = False
    """Open the app in the default web browser."""
    view_width: int = 192
    """Width in pixels of the render of your own (still) browser view; a third of it while moving."""
    render_duty: float = 0.25
    """At most this fraction of wall time goes to browser renders (they share the trainer's lock)."""


def train_config(cfg: TrainConfig) -> TrainConfig:
    """The plain TrainConfig part of an AppConfig (what the trainer and its run folder see)."""
    return TrainConfig(**{f.name: getattr(cfg, f.name) for f in fields(TrainConfig)})


def _scene_key(cfg: TrainConfig) -> tuple:
    return (cfg.scene, str(cfg.data) if cfg.data is not None else None, cfg.res)


def check_run_input(cfg: TrainConfig) -> SceneData:
    """Load the scene and build its mirror plane before serving: bad input fails in one line, at once."""
    scene = load_scene(cfg.scene, cfg.data, cfg.res)
    make_mirror_set(make_split(scene, cfg.config).inputs, cfg.mirror_plane, scene.symmetry_plane)
    return scene


def _fmt_time(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


class App(Observer):
    """Viser server + background trainer + GUI. Start with `start()`, end with `stop()`.

    It is the `RunView` (viz/run_view.py) its panels read: setup, step, mirror_c2w, render.
    """

    def __init__(self, cfg: AppConfig, scene: SceneData | None = None) -> None:
        self.cfg = cfg
        self._preloaded = (_scene_key(cfg), scene) if scene is not None else None  # for the first run
        self.server = viser.ViserServer(host=cfg.host, port=cfg.port, label="flipviz", verbose=False)
        self._set_initial_camera(np.zeros(3), 4.0)
        self.port = self.server.get_port()  # the port actually bound (viser moves on when it is busy)
        shown = "localhost" if cfg.host in ("0.0.0.0", "::", "") else cfg.host
        self.url = f"http://{shown}:{self.port}"
        self.worker = RenderWorker(cfg.render_duty)
        self.scene = RunScene(self.server)
        self.trainer = None  # flipviz.training.trainer.Trainer of the current run
        self.setup: SetupEvent | None = None
        self.mirror_c2w: np.ndarray | None = None
        self.step = 0
        self.status = "starting"
        self.message = ""
        self.restarts = 0
        self._thread: threading.Thread | None = None
        self._run_lock = threading.Lock()  # serialises start / restart / stop
        self._trainer_lock = threading.Lock()
        self._gen = 0  # run generation: bumped whenever a run is stopped
        self._ev_lock = threading.Lock()
        self._pending_setup: SetupEvent | None = None
        self._last_step: StepEvent | None = None
        self._last_images: ImagesEvent | None = None
        self._test_psnr: float | None = None
        self._hist_step: list[float] = []
        self._hist_psnr: list[float] = []
        self._closing = threading.Event()
        self._busy_mark, self._render_share = (time.monotonic(), 0.0), 0.0
        self._ui_thread = threading.Thread(target=self._ui_loop, name="flipviz-ui", daemon=True)
        self._build_gui()
        self.views = ViewportRenderer(
            self.worker, self.render, lambda: self.status == "running",
            low_width=max(32, cfg.view_width // 3), full_width=cfg.view_width,
        )  # fmt: skip
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(lambda c: self.views.remove_client(c.client_id))

    # ---- GUI --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=(240, 130, 20))
        tabs = gui.add_tab_group()
        with tabs.add_tab("Train", viser.Icon.PLAYER_PLAY):
            self.progress_md = gui.add_markdown("_Starting..._")
            self.progress_bar = gui.add_progress_bar(0.0, animated=False, color="orange")
            self.plot = gui.add_uplot(
                (np.array([0.0, 1.0]), np.array([0.0, 0.0])),
                (
                    {"label": "step"},
                    {"label": "PSNR (train batch, dB)", "stroke": "#f08214", "width": 2},
                ),
                title="PSNR", scales={"x": {"time": False}}, aspect=1.6,
            )  # fmt: skip
            self.pause_btn = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE)
            self.resume_btn = gui.add_button("Resume", icon=viser.Icon.PLAYER_PLAY, disabled=True)
            with gui.add_folder("Restart", expand_by_default=True):
                self.method_dd = gui.add_dropdown("Method", METHODS, initial_value=self.cfg.method)
                self.config_dd = gui.add_dropdown(
                    "Configuration", tuple(str(i) for i in range(1, 9)), initial_value=str(self.cfg.config)
                )
                self.steps_num = gui.add_number("Steps", int(self.cfg.steps), min=1, step=1)
                self.restart_btn = gui.add_button("Restart training", icon=viser.Icon.REFRESH)
            self.your_view = gui.add_folder("Your view")
        with tabs.add_tab("Views", viser.Icon.CAMERA):
            with gui.add_folder("Snap to view"):
                self.snap = SnapToView(self.server, self.worker, self)
            with gui.add_folder("Novel cameras"):
                self.novel = NovelCameras(self.server, self.worker, self)
        with tabs.add_tab("Mirror", viser.Icon.FLIP_VERTICAL):
            self.mirror = MirrorLesson(self.server, self.worker, self, self.scene, self.restart_with_plane)
        with tabs.add_tab("Show", viser.Icon.EYE):
            for g, (label, _) in GROUPS.items():
                cb = gui.add_checkbox(label, self.scene.visible[g])
                cb.on_update(lambda ev, g=g: self.scene.set_visible(g, ev.target.value))
        self.pause_btn.on_click(lambda _: self.pause())
        self.resume_btn.on_click(lambda _: self.resume())
        self.restart_btn.on_click(lambda _: self.restart(self._restart_config()))

    def restart_with_plane(self, plane: Plane) -> None:
        """Retrain with `plane` as the mirror plane (with Flip+U unless a Flip method is running)."""
        method = self.cfg.method if self.cfg.method in ("flip", "flip+u") else "flip+u"
        self.restart(replace(self.cfg, mirror_plane=plane_to_arg(plane), method=method))

    def _restart_config(self) -> AppConfig:
        return replace(
            self.cfg, method=self.method_dd.value, config=int(self.config_dd.value), steps=int(self.steps_num.value)
        )

    def _set_initial_camera(self, center: np.ndarray, radius: float) -> None:
        """New tabs start outside the camera sphere, above the camera ring, looking at its centre (z up)."""
        cam = self.server.initial_camera
        cam.position = center + radius * np.array([1.0, -1.0, 1.9])
        cam.look_at = center
        cam.fov = np.deg2rad(50.0)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        self.views.add_client(client, folder=self.your_view)

    # ---- training control -------------------------------------------------------------------
    def start(self) -> "App":
        self._ui_thread.start()
        with self._run_lock:
            self._start_run(self.cfg)
        return self

    def _start_run(self, cfg: AppConfig) -> None:
        self.cfg = cfg
        self.status, self.message, self.step = "starting", "", 0
        self._thread = threading.Thread(target=self._train_thread, args=(cfg, self._gen), name="flipviz-train", daemon=True)
        self._thread.start()

    def _train_thread(self, cfg: AppConfig, gen: int) -> None:
        from flipviz.training.trainer import Trainer

        tcfg = train_config(cfg)
        scene = self._preloaded[1] if self._preloaded and self._preloaded[0] == _scene_key(cfg) else None
        try:
            trainer = Trainer(tcfg, scene=scene)
        except Exception as e:  # bad data / plane: show it, keep serving
            self.status, self.message = "error", f"{type(e).__name__}: {e}"
            log.error("could not start training: %s", self.message)
            return
        trainer.add_observer(self)
        if not cfg.no_rrd:
            try:
                from flipviz.viz.rerun_observer import make_rerun_observer

                trainer.add_observer(make_rerun_observer(tcfg, trainer.run_dir))
            except Exception as e:
                log.warning("Rerun recording disabled: %s: %s", type(e).__name__, e)
        with self._trainer_lock:
            if gen != self._gen:  # stopped or restarted while the trainer was being built
                return
            self.trainer = trainer
        self.on_setup(trainer.setup_event)
        self.status = "running"
        trainer.run()

    def pause(self) -> None:
        if self.trainer is not None and self.status == "running":
            self.trainer.pause()
            self.status = "paused"
            self.pause_btn.disabled, self.resume_btn.disabled = True, False

    def resume(self) -> None:
        if self.trainer is not None and self.status == "paused":
            self.trainer.resume()
            self.status = "running"
            self.pause_btn.disabled, self.resume_btn.disabled = False, True

    def _stop_run(self) -> None:
        """Stop the trainer thread and wait for it (the trainer saves its checkpoint)."""
        with self._trainer_lock:
            self._gen += 1  # a trainer still being built will not start
            trainer = self.trainer
        if trainer is not None:
            trainer.stop()
        if self._thread is not None:
            self._thread.join()
        self.trainer = None

    def restart(self, cfg: AppConfig) -> None:
        """Stop the current run and train `cfg` from scratch (new run folder); resets the scene."""
        with self._run_lock:
            if self._closing.is_set():
                return
            self.restarts += 1
            self.status = "restarting"
            self.progress_md.content = "_Stopping the current run..._"
            self._stop_run()
            self.worker.cancel(lambda k: True)
            self.scene.clear()
            self.mirror.clear()
            out = None if self.cfg.out is None else Path(self.cfg.out) / f"restart{self.restarts}"
            cfg = replace(cfg, out=out, resume=None, rrd=None)
            self.pause_btn.disabled, self.resume_btn.disabled = False, True
            self._start_run(cfg)

    def stop(self) -> None:
        """Stop training (joined: checkpoint and recording flushed), the renders and the server."""
        self._closing.set()
        with self._run_lock:
            self._stop_run()
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

    # ---- Observer (called in the trainer's thread: copy and return) -------------------------
    def on_setup(self, event: SetupEvent) -> None:
        with self._ev_lock:
            if event is self.setup or event is self._pending_setup:
                return
            self._pending_setup = event

    def on_step(self, event: StepEvent) -> None:
        with self._ev_lock:
            self._last_step = event
            self.step = event.step
            if event.mirror_c2w is not None:
                self.mirror_c2w = event.mirror_c2w
            p = event.scalars.get("psnr")
            if p is not None and np.isfinite(p):
                self._hist_step.append(float(event.step))
                self._hist_psnr.append(float(p))

    def on_images(self, event: ImagesEvent) -> None:
        with self._ev_lock:
            self._last_images = event
            if "test_psnr" in event.scalars:
                self._test_psnr = float(event.scalars["test_psnr"])

    def on_end(self, event: EndEvent) -> None:
        self.step = event.step
        self.status = event.status
        self.message = event.message
        if "psnr" in event.metrics:
            self.message = f"unobserved views PSNR {event.metrics['psnr']:.2f} dB" + (
                f" ({event.message})" if event.message else ""
            )

    # ---- UI thread --------------------------------------------------------------------------
    def _ui_loop(self, period: float = 0.25) -> None:
        last_plot = last_mirrors = 0.0
        while not self._closing.wait(period):
            try:
                with self._ev_lock:
                    setup, self._pending_setup = self._pending_setup, None
                    if setup is not None:
                        self.setup, self.mirror_c2w, self._last_step, self._test_psnr = setup, None, None, None
                        self._hist_step, self._hist_psnr = [], []
                    images, self._last_images = self._last_images, None
                    step_ev = self._last_step
                if setup is not None:
                    self._new_run(setup)
                now = time.monotonic()
                if step_ev is not None and now - last_mirrors > 0.5 and step_ev.mirror_c2w is not None:
                    self.scene.update_mirrors(step_ev.mirror_c2w)
                    last_mirrors = now
                if now - last_plot > 1.0:
                    self._update_plot()
                    last_plot = now
                if images is not None:
                    self.mirror.on_images(images)
                self._update_progress(step_ev)
            except Exception:
                log.exception("UI update failed")

    def _new_run(self, setup: SetupEvent) -> None:
        self._set_initial_camera(np.asarray(setup.sphere_center), float(setup.sphere_radius))
        self.scene.build(setup)
        self.mirror.clear()
        self.mirror.build(setup)
        self.snap.rebuild()
        self.method_dd.value, self.config_dd.value = self.cfg.method, str(self.cfg.config)
        self.steps_num.value = int(self.cfg.steps)
        self.views.request_all()

    def _update_plot(self) -> None:
        with self._ev_lock:
            x, y = np.array(self._hist_step), np.array(self._hist_psnr)
        if len(x) < 2:
            return
        if len(x) > 400:
            idx = np.linspace(0, len(x) - 1, 400).astype(int)
            x, y = x[idx], y[idx]
        self.plot.data = (x, y)

    def _update_progress(self, ev: StepEvent | None) -> None:
        setup = self.setup
        head = f"**{setup.scene} | {setup.method} | configuration {setup.config}**" if setup else "**flipviz**"
        parts = [f"status: **{self.status}**"]
        if ev is not None:
            s = ev.scalars
            rate = ev.step / ev.elapsed_s if ev.elapsed_s > 0 else float("nan")
            eta = (ev.total_steps - ev.step) / rate if rate > 0 and self.status == "running" else None
            parts += [
                f"step **{ev.step}** / {ev.total_steps}",
                f"loss {s.get('loss', float('nan')):.4f}",
                f"PSNR {s.get('psnr', float('nan')):.2f} dB",
                f"{rate:.1f} steps/s",
            ]
            if eta is not None:
                parts.append(f"ETA {_fmt_time(eta)}")
            self.progress_bar.value = 100.0 * ev.step / max(1, ev.total_steps)
        if self._test_psnr is not None:
            parts.append(f"test PSNR **{self._test_psnr:.2f} dB**")
        now, busy = time.monotonic(), self.worker.busy_s
        t0, b0 = self._busy_mark
        if now - t0 > 5.0:
            self._render_share, self._busy_mark = (busy - b0) / (now - t0), (now, busy)
        parts.append(f"browser renders {100 * self._render_share:.0f}% of the time")
        text = head + "\n\n" + " | ".join(parts)
        if self.message:
            text += f"\n\n_{self.message}_"
        if setup is not None and self.trainer is not None:
            text += f"\n\nrun folder: `{self.trainer.run_dir}`"
        if self.progress_md.content != text:
            self.progress_md.content = text


def run_app(cfg: AppConfig) -> None:
    """Serve the app and train until Ctrl-C (training keeps being served after it finishes)."""
    logging.basicConfig(level=logging.WARNING, format="[flipviz] %(message)s")
    app = App(cfg, scene=check_run_input(cfg)).start()
    print(f"[flipviz] app running at {app.url}  (Ctrl-C to stop)", flush=True)
    if cfg.open_browser:
        webbrowser.open(app.url)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("[flipviz] stopping: saving the checkpoint and the recording...", flush=True)
    finally:
        app.stop()
        print("[flipviz] stopped.", flush=True)
