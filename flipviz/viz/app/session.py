"""The app's training run: one `Trainer` at a time, trained in a background thread.

    session = TrainingSession(cfg, observers=[events])  # the app's RunEvents observe every run
    session.start()                                    # builds the trainer in its thread, trains
    session.restart(other_cfg, on_stopped=clear_gui)   # the run stops (checkpoint saved), a new one starts
    session.pause(); session.resume(); session.stop()

Start, restart and stop hold one lock, so that they never interleave. A trainer that is still being
built (its scene loading, rays cast) when its run is stopped never starts training: each stop
counts a generation, and the thread building it checks its own before it takes over.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

from flipviz.data import SceneData
from flipviz.files import next_free
from flipviz.training.artifacts import prune_checkpoints
from flipviz.training.checkpoint import CHECKPOINT_NAME
from flipviz.training.config import TrainConfig
from flipviz.training.events import EndEvent, Observer

log = logging.getLogger("flipviz.app")


def train_config(cfg: TrainConfig) -> TrainConfig:
    """The plain TrainConfig part of an AppConfig (what the trainer and its run folder see)."""
    return TrainConfig.from_settings(**cfg.settings())


def _scene_key(cfg: TrainConfig) -> tuple:
    return (cfg.data.scene, str(cfg.data.path) if cfg.data.path is not None else None, cfg.data.res)


class TrainingSession(Observer):
    """The current run of the app and its lifecycle: status is starting | running | paused |
    restarting | finished | stopped | error (the trainer's end status, or why it could not start)."""

    def __init__(
        self,
        cfg: TrainConfig,
        observers: Sequence[Observer],
        scene: SceneData | None = None,
        checkpoints_mb: float = 0.0,
    ) -> None:
        """`checkpoints_mb`: the disk the replaced runs' checkpoints may keep (--restart-checkpoints-mb)."""
        self.cfg = cfg  # the current run's settings (an AppConfig in the app)
        self.trainer = None  # flipviz.training.trainer.Trainer of the current run, once built
        self.status, self.message = "starting", ""
        self.restarts = 0
        self.run_dirs: list[Path] = []  # every run folder this session wrote, in order
        self._observers = list(observers)
        self._checkpoints_bytes = checkpoints_mb * 1e6
        self._base_out = cfg.output.out  # restarts write beside it: <out>-restart1, <out>-restart2, ...
        self._preloaded = (_scene_key(cfg), scene) if scene is not None else None  # for the first run
        self._lock = threading.Lock()  # start / restart / stop, and a built trainer taking over
        self._gen = 0  # run generation: counted up whenever a run is stopped
        self._thread: threading.Thread | None = None
        self._closed = False

    # ---- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        with self._lock:
            self._start(self.cfg)

    def restart(self, cfg: TrainConfig, on_stopped: Callable[[], None] = lambda: None) -> bool:
        """Stop the current run and train `cfg` from scratch in a new run folder; `on_stopped` runs
        between the two (the app clears its views). The replaced run keeps its metrics, renders and
        recording, and its checkpoint while the replaced runs' checkpoints fit
        `checkpoints_mb` (the oldest go first). False when the session is closed."""
        with self._lock:
            if self._closed:
                return False
            self.restarts += 1
            self.status = "restarting"
            log.warning("restarting: the current run stops (its checkpoint stays in its folder)")
            self._stop_run()
            for ckpt in prune_checkpoints(self.run_dirs, self._checkpoints_bytes):
                log.info("deleted %s (over --restart-checkpoints-mb)", ckpt)
            on_stopped()
            out = None if self._base_out is None else next_free(f"{self._base_out}-restart{self.restarts}")
            self._start(cfg.with_settings(out=out, resume=None, rrd=None))
            return True

    def stop(self) -> None:
        """Stop training and wait for it (the trainer saves its checkpoint and recording); no run starts after."""
        with self._lock:
            self._closed = True
            self._stop_run()

    def pause(self) -> bool:
        """Pause a running run; False when there was none to pause."""
        if self.trainer is None or self.status != "running":
            return False
        self.trainer.pause()
        self.status = "paused"
        return True

    def resume(self) -> bool:
        """Resume a paused run; False when there was none to resume."""
        if self.trainer is None or self.status != "paused":
            return False
        self.trainer.resume()
        self.status = "running"
        return True

    def building(self) -> bool:
        """A trainer is still being built (scene loading, ray casting) in the training thread."""
        return self.trainer is None and self._thread is not None and self._thread.is_alive()

    def _start(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.status, self.message = "starting", ""
        self._thread = threading.Thread(target=self._train, args=(cfg, self._gen), name="flipviz-train", daemon=True)
        self._thread.start()

    def _stop_run(self) -> None:
        """Stop the trainer and join its thread. A trainer still being built is not waited for: it
        has nothing to save and will not start (its generation is gone); its daemon thread ends."""
        self._gen += 1
        trainer, self.trainer = self.trainer, None
        if trainer is not None:
            trainer.stop()
            if self._thread is not None:
                self._thread.join()

    def _train(self, cfg: TrainConfig, gen: int) -> None:
        """The training thread: build the trainer (the scene, the mirrors, the rays), then train."""
        from flipviz.training.trainer import Trainer

        tcfg = train_config(cfg)
        scene = self._preloaded[1] if self._preloaded and self._preloaded[0] == _scene_key(cfg) else None
        try:
            trainer = Trainer(tcfg, scene=scene, on_phase=lambda text: self._phase(gen, text))
        except Exception as e:  # bad data / plane: shown in the app, which keeps serving
            self.status, self.message = "error", f"{type(e).__name__}: {e}".splitlines()[0]
            log.error("could not start training: %s", self.message)
            return
        trainer.add_observer(self)
        for obs in self._observers:
            trainer.add_observer(obs)
        if not cfg.output.no_rrd:
            try:
                from flipviz.viz.rerun.observer import make_rerun_observer

                trainer.add_observer(make_rerun_observer(tcfg, trainer.run_dir, bake=trainer.point_cloud))
            except Exception as e:
                log.warning("Rerun recording disabled: %s: %s", type(e).__name__, e)
        with self._lock:
            if gen != self._gen:  # stopped or restarted while the trainer was being built
                trainer.close()
                return
            self.trainer = trainer
            self.run_dirs.append(trainer.run_dir)
            self.status, self.message = "running", ""
        log.warning("training %s in %s", tcfg.method, trainer.run_dir)
        trainer.run()

    # ---- what the app reads -----------------------------------------------------------------
    def run_dir(self) -> Path | None:
        trainer = self.trainer
        return trainer.run_dir if trainer is not None else None

    def scene(self) -> SceneData | None:
        """The current run's scene (None before its trainer is built)."""
        trainer = self.trainer
        return trainer.scene if trainer is not None else None

    def previous_run(self) -> Path | None:
        """The newest run folder trained before the current one that still holds its checkpoint."""
        current = self.run_dir()
        return next((d for d in reversed(self.run_dirs) if d != current and (d / CHECKPOINT_NAME).is_file()), None)

    def _phase(self, gen: int, text: str) -> None:
        """What the trainer being built is doing (its warm-up: 10-30 s), in the Train tab's status."""
        if gen == self._gen:
            self.message = text

    def on_end(self, event: EndEvent) -> None:
        self.status = event.status
        self.message = event.message
        if "psnr" in event.metrics:
            scored = TrainConfig.from_settings(**event.metrics["settings"]).eval.words()  # flipviz's, or the authors'
            self.message = f"PSNR {event.metrics['psnr']:.2f} dB in {scored}" + (
                f" ({event.message})" if event.message else ""
            )
        log.warning("run %s at step %d%s", event.status, event.step, f": {self.message}" if self.message else "")
