"""The training loop of the five methods, with events, a thread-safe render, pause/resume/stop.

    trainer = Trainer(cfg)              # setup.py: split -> mirrors -> training set -> model, Flip hooks
    trainer.add_observer(obs)           # events.py: on_setup / on_step / on_images / on_end
    metrics = trainer.run()             # blocking; stop() / pause() / resume() from other threads

One step (`_train_step`), a NeRF step with Just Flip's hooks (flip.py, paper Sec. IV):
    idx      = batch_rays random pixels of the training views        (R,)
    poses    = flip.poses(): every view's c2w; mirrors follow the     (V, 4, 4)
               refined plane and BA
    o, d     = rays of the pixels from their views' poses             (R, 3) each
    out      = render(o, d): rgb (R, 3), beta2, sigma_mean (R,)
    loss     = flip.loss(out, target, view, step) + regulariser       (model/objective.py)
then the field's optimiser steps, and `flip.after_step` moves what Flip adds (poses, plane) and says
what comes next (`_act`: go on; build the run again around the field; restart the field or roll it
back to where the mirrors joined).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import datetime
from functools import partial
from pathlib import Path

import numpy as np
import torch

from flipviz.data.cameras import Camera, rays_from_c2w
from flipviz.data.dataset import SceneData
from flipviz.errors import UserError
from flipviz.files import FolderLock, cannot_write, signals_deferred
from flipviz.model.objective import psnr
from flipviz.model.radiance import RenderCancelled
from flipviz.runtime import keep_freed_memory
from flipviz.training import artifacts
from flipviz.training import checkpoint as ckpt
from flipviz.training import evaluate as ev
from flipviz.training.artifacts import PLANE_FILE
from flipviz.training.config import TrainConfig
from flipviz.training.events import EndEvent, ImagesEvent, Observer, StepEvent
from flipviz.training.flip import Action
from flipviz.training.pose_tuning import eval_renders
from flipviz.training.setup import (
    RunSetup,
    build_run,
    evaluation_views,
    fresh_model,
    join_mirrors,
    load_scene_for,
    setup_event,
)

log = logging.getLogger("flipviz.training")
WARM_UP_SAID = 50  # on_phase hears every this many warm-up steps


class NonFiniteLoss(RuntimeError):
    pass


def scene_label(cfg: TrainConfig) -> str:
    return Path(cfg.data.path).name if cfg.data.path is not None else cfg.data.scene


def default_run_dir(cfg: TrainConfig) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{scene_label(cfg)}-{cfg.method}-{cfg.data.config}-{stamp}"


class Trainer:
    def __init__(
        self, cfg: TrainConfig, scene: SceneData | None = None, on_phase: Callable[[str], None] | None = None
    ) -> None:
        """A run to train (a finished one opens to look at as a `saved_run.Run`, with no trainer). `on_phase`
        hears, in words, what setup is doing before the first event (the auto plane's warm-up: 10-30 s)."""
        self.cfg = cfg.validate()
        self._say = on_phase or (lambda _: None)
        self.run_dir = Path(cfg.output.out) if cfg.output.out is not None else default_run_dir(cfg)
        self._lock_file = FolderLock(self.run_dir)  # the run folder, ours until run() ends
        try:
            self._set_up(scene)
        except BaseException:  # refused or interrupted during setup: no run folder is left behind empty
            self._lock_file.abandon()
            raise
        self.setup_event = setup_event(
            self.run_dir.name, cfg, self.scene, self.split, self.mirrors, self.spec.mirrors, self.plane_estimate
        )

    def _set_up(self, scene: SceneData | None) -> None:
        cfg = self.cfg
        artifacts.take_over(self.run_dir, cfg)
        keep_freed_memory()  # a step's large temporaries reuse the last step's memory (runtime.py)
        torch.manual_seed(cfg.engine.seed)
        self._gen = torch.Generator().manual_seed(cfg.engine.seed)
        self.scene = scene if scene is not None else load_scene_for(cfg)
        resumed = Path(cfg.output.resume) if cfg.output.resume is not None else None  # a checkpoint or its run folder
        saved = (resumed if resumed.is_dir() else resumed.parent) / PLANE_FILE if resumed is not None else None
        rs = build_run(cfg, self.scene, saved, say=self._say)
        self._adopt(rs)
        self.opt_field = self.model.make_optimizer()
        self.step = 0
        self.field_start = 0  # the field's step is step - field_start: moved by a restart or a rollback (--after-drop)
        self.train_seconds = 0.0  # spent in training steps (not in pauses or image renders)
        self._observers: list[Observer] = []
        self._lock = threading.RLock()  # one lock for a training step and for render()
        self._running = threading.Event()
        self._running.set()  # set = not paused
        self._stop = threading.Event()
        warm_up = self.flip.warm_up  # steps before the run is whole (flip.py: auto's plane from the field)
        while self.step < warm_up:
            if self.step % WARM_UP_SAID == 0:
                self._say(f"warm-up for the auto plane: step {self.step} / {warm_up} of the inputs alone")
            self._step()
        field_step = self.step - self.field_start  # where the mirrors joined: what Action.ROLL_BACK returns to
        self._joined = ckpt.FieldSnapshot.take(self.model, self.opt_field, self._gen, field_step)
        if self.plane_estimate is not None:
            artifacts.write_plane(self.run_dir, self.plane_estimate)
        if cfg.output.resume is not None:
            self._load(cfg.output.resume)

    def _adopt(self, rs: RunSetup) -> None:
        self.spec, self.split, self.mirrors, self.training = rs.spec, rs.split, rs.mirrors, rs.training
        self.plane_estimate, self.model, self.flip = rs.estimate, rs.model, rs.flip

    # ------------------------------------------------------------------ public control API
    def add_observer(self, obs: Observer) -> None:
        self._observers.append(obs)

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    @property
    def total_steps(self) -> int:
        """The steps the run takes: cfg.engine.steps, plus the steps before a restart of the field."""
        return self.field_start + self.cfg.engine.steps

    def stop(self) -> None:
        self._stop.set()
        self._running.set()  # a paused loop must wake up to stop

    @torch.no_grad()
    def render(
        self, camera: Camera, outputs=("rgb", "depth", "opacity", "beta2"), cancellable: bool = False
    ) -> dict[str, np.ndarray]:
        """Render a full image from `camera` with the current field; thread-safe. `cancellable`: a stop
        (stop()) ends it between chunks of rays with RenderCancelled (the run's own evaluations)."""
        with self._lock:
            out = self.model.render_image(camera, cancel=self._stop.is_set if cancellable else None)
        return {k: out[k] for k in outputs if k in out}

    def _evaluation(self, what: str, n: int) -> Callable[[Camera], dict[str, np.ndarray]]:
        """`render` for an evaluation of `n` views: a stop ends it within a chunk of rays; a slow one says on_phase
        which view it is at (evaluate.py: announced)."""
        return ev.announced(partial(self.render, cancellable=True), self._say, what, n)

    @torch.no_grad()
    def point_cloud(self, min_alpha: float = 0.05, max_points: int = 150_000) -> dict[str, np.ndarray]:
        """The current field as coloured points (see RadianceModel.point_cloud); thread-safe."""
        with self._lock:
            return self.model.point_cloud(min_alpha, max_points)

    # ------------------------------------------------------------------ one step
    def _step(self) -> dict:
        """One training step, timed, then what Flip asks for after it; its scalars."""
        t0 = time.perf_counter()
        with self._lock:
            scalars, action = self._train_step()
        self.train_seconds += time.perf_counter() - t0
        with self._lock:
            self._act(action)
        return scalars

    def _train_step(self) -> tuple[dict, Action]:
        cfg, bank = self.cfg, self.training.bank
        field_step = self.step - self.field_start  # the field's schedules count from its start
        with signals_deferred():  # an interrupt never leaves half-upsampled grids or a stale optimiser
            if self.model.update_schedule(field_step, cfg.engine.steps):  # grids upsampled: new parameters
                self.opt_field = self.model.make_optimizer()
        self.model.adjust_lr(self.opt_field, *self.flip.field_lr(field_step))
        # (R,) random pixels: the inputs' alone before the mirrors join, and after a drop
        idx = self.flip.sample(cfg.engine.batch_rays, self._gen, self.step)
        view = bank.view[idx]
        o, d = rays_from_c2w(self.flip.poses().index_select(0, view), bank.dirs_cam[idx])  # (R, 3) each; mirrors: BA's
        out = self.model.render_rays(o, d, training=True)
        target = bank.rgb[idx]
        total = self.flip.loss(out, target, view, field_step) + self.model.regulariser()
        if not torch.isfinite(total):
            raise NonFiniteLoss(f"loss became {float(total.detach())} at step {self.step + 1}")
        self.opt_field.zero_grad(set_to_none=False)  # in place: the grids' gradients are kept (model/optim.py)
        total.backward()
        self.opt_field.step()
        action = self.flip.after_step(self.step)
        self.step += 1
        scalars = {
            "loss": float(total.detach()),
            "psnr": psnr(float(((out["rgb"].detach() - target) ** 2).mean())),
            "lr_field": float(self.opt_field.param_groups[0]["lr"]),
            **self.flip.scalars(),
        }
        return scalars, action

    def _act(self, action: Action) -> None:
        """What Flip asked for after a step (flip.py: Action)."""
        if action is Action.JOIN:  # the run built again around its field (setup.py: join_mirrors)
            self._say("estimating the mirror plane from the warmed-up field, then the mirrored views join")
            rs = join_mirrors(self.cfg, self.scene, self.model, self.step)
            self._adopt(rs)
            if rs.start_over:  # a fresh field and sampler from step 0, seeded as B/L's
                self._new_field(0)
                self.step, self.train_seconds = 0, 0.0
        elif action is Action.RESTART_FIELD:
            log.warning("step %d: a fresh field trains the inputs alone (--after-drop restart)", self.step)
            self._new_field(self.step)
        elif action is Action.ROLL_BACK:  # the run grows by the steps since the join
            log.warning("step %d: the field goes back to step %d, where the mirrors joined", self.step, self.flip.start)
            with signals_deferred():
                self.opt_field = self._joined.restore(self.model, self._gen)
                self.field_start = self.step - self._joined.field_step

    def _new_field(self, start: int) -> None:
        """A fresh field without a variance head (no mirrored ray is trained any more) and sampler, from step
        `start` for the full cfg.engine.steps, seeded as B/L's first ones (the run then ends as B/L would)."""
        with signals_deferred():
            torch.manual_seed(self.cfg.engine.seed)
            self.model = fresh_model(self.cfg, self.scene, with_beta=False)
            self.opt_field = self.model.make_optimizer()
            self.field_start = start
            self._gen = torch.Generator().manual_seed(self.cfg.engine.seed)

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict:
        """Train to total_steps (cfg.engine.steps, longer after a restart; or until stopped / NaN); returns the
        final metrics."""
        cfg = self.cfg
        self._emit("on_setup", self.setup_event)
        status, message = "finished", ""
        try:
            while self.step < self.total_steps:
                if not self._running.is_set():
                    self._running.wait()  # paused: block between steps, without the render lock
                if self._stop.is_set():
                    status = "stopped"
                    break
                scalars = self._step()
                if self.step % cfg.output.log_every == 0 or self.step == self.total_steps:
                    live = self.flip.live()  # the mirrored poses and the plane now
                    self._emit("on_step", StepEvent(self.step, self.total_steps, self.train_seconds, scalars, **live))
                every = cfg.output.images_every
                if every > 0 and self.step % every == 0 and self.step < self.total_steps:
                    self._emit("on_images", self._images_event())
                    self._say("")  # (what it said of a slow evaluation is over)
                if cfg.output.checkpoint_every > 0 and self.step % cfg.output.checkpoint_every == 0:
                    self.save_checkpoint()
        except NonFiniteLoss as e:
            status, message = "nan", f"{e}; stopped, last good checkpoint kept in {self.run_dir}"
            log.error("%s", message)
        except KeyboardInterrupt:
            status, message = "stopped", "interrupted"
        except RenderCancelled:  # stopped during a periodic evaluation
            status = "stopped"
        except UserError as e:  # e.g. the disk is full: one line, the last good checkpoint stays
            status, message = "error", str(e)
        except Exception as e:
            status, message = "error", f"{type(e).__name__}: {e}"
            log.exception("training failed")
        if status in ("finished", "stopped") and not ckpt.state_is_finite(self.model.state_dict()):
            status, message = (
                "nan",
                f"the model is not finite at step {self.step}; last good checkpoint kept in {self.run_dir}",
            )
        metrics: dict = {}
        try:
            if status in ("finished", "stopped") and self.save_checkpoint() is not None:
                asked = self._stop.is_set()  # stop(): a restart or the app closing waits for no evaluation
                if status == "finished" or (cfg.output.eval_on_stop and not asked):
                    renders = self.render_tests()  # rendered once, for the scores and the last images
                    metrics = self.evaluate(renders)
                    self._emit("on_images", self._images_event(renders))
        except (KeyboardInterrupt, RenderCancelled):  # a second Ctrl-C, or a stop: no scores, the checkpoint stays
            status = "stopped"
            message = f"stopped during the final evaluation; checkpoint kept in {self.run_dir}"
            metrics = {}
        except UserError as e:
            status, message, metrics = "error", str(e), {}
        finally:
            self.close()
        metrics = dict(metrics, status=status, message=message, steps=self.step, run_dir=str(self.run_dir))
        self._emit("on_end", EndEvent(self.step, status, message, metrics))
        return metrics

    # ------------------------------------------------------------------ evaluation
    def render_tests(self) -> list[dict[str, np.ndarray]]:
        """Renders (rgb, depth, opacity, beta2) of the unobserved test views, in split order."""
        render = self._evaluation("rendering the unobserved views", len(self.split.tests))
        return [render(v.camera) for v in self.split.tests]

    def evaluate(self, renders: list[dict[str, np.ndarray]] | None = None, write: bool = True) -> dict:
        """Score the run (cfg.eval: the unobserved test views at their poses, `renders` when given; or the
        orbit's other views, or tuned poses: the authors' protocol); write metrics.json, test_renders/,
        transforms.json."""
        e = self.cfg.eval
        tests = evaluation_views(self.cfg, self.scene, self.split)
        if e.eval_views != "unobserved" or e.eval_tune_steps > 0 or e.eval_every > 1 or renders is None:
            align = self.flip.test_alignment()
            render = self._evaluation("evaluating", len(tests))
            renders = eval_renders(render, self.model, tests, e.eval_tune_steps, align, self.cfg.engine.seed)
        m = ev.score_renders(self.scene, tests, renders)
        m.update(train_seconds=self.train_seconds, steps=self.step, scored_views=len(tests), **self.report())
        if write:
            preds = [o["rgb"] for o in renders]
            with cannot_write(self.run_dir, "the results in"):
                artifacts.write_test_renders(self.run_dir, [v.name for v in tests], preds, [v.rgb for v in tests])
                if self.training.mirror_ids:
                    mirrors = [v.image for v in self.training.mirror_views]
                    artifacts.write_transforms(self.run_dir, self.flip.mirror_cameras(), mirrors)
                artifacts.write_metrics(self.run_dir, m)
        return m

    def report(self) -> dict:
        """What a run's metrics say besides its scores: the run and its settings, and Flip's part (its
        mirrors' coverage of the unobserved views, its plane and its mirrored poses)."""
        s = self.cfg.to_dict()
        m = dict(method=self.cfg.method, config=self.split.config, scene=self.scene.name, settings=s)
        return m | {"mirror_plane": s["mirror_plane"]} | self.flip.report([v.camera for v in self.split.tests])

    def close(self) -> None:
        """Give the run folder back without training (run() does it when it ends)."""
        self._lock_file.release()

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "field_start": self.field_start,
            "config": self.cfg.to_dict(),
            "model": self.model.state_dict(),
            "opt_field": self.opt_field.state_dict(),
            **self.flip.state_dict(),  # poses, opt_pose, plane, opt_plane
            "mirror_c2w": None if (c2w := self.flip.mirror_c2w()) is None else torch.from_numpy(c2w),  # for saved_run
            "train_seconds": self.train_seconds,
            "rng": self._gen.get_state(),
            "torch_rng": torch.get_rng_state(),
        }

    def save_checkpoint(self) -> Path | None:
        """Write checkpoint.pt (atomically), unless the state is not finite (keeps the last good one).

        A failed write (a full disk, a read-only folder) is a UserError naming the file; the last
        good checkpoint stays and no temporary file is left.
        """
        path = self.run_dir / ckpt.CHECKPOINT_NAME
        with self._lock:
            state = self.checkpoint_state()
            if not all(ckpt.state_is_finite(state[k] or {}) for k in ("model", "poses", "plane")):
                log.warning("not saving a non-finite state at step %d; the last good checkpoint is kept", self.step)
                return None
            return ckpt.save_checkpoint(path, state)

    def _load(self, path: Path | str) -> None:
        state = ckpt.load_checkpoint(path, map_location=self.model.device)
        ckpt.check_resumable(state, self.cfg.settings(), path, named_scene=self.cfg.data.path is None)
        try:  # a crafted or foreign checkpoint fails in many ways below: each is one line
            self.flip.load_state_dict(state)
            start = ckpt.counter(state, "field_start", 0)
            if self.flip.field_restarted:  # a fresh field after the mirrors were dropped: no variance head
                self._new_field(start)
            self.field_start = start  # a restart's or a rollback's (flip.py: Action)
            self.model.load_state_dict(state["model"])
            self.opt_field = self.model.make_optimizer()
            self.opt_field.load_state_dict(state["opt_field"])
            self.step, self.train_seconds = ckpt.counter(state, "step"), float(state.get("train_seconds", 0.0))
            if state.get("rng") is not None:
                self._gen.set_state(state["rng"])
            if state.get("torch_rng") is not None:
                torch.set_rng_state(state["torch_rng"])
        except ckpt.MISFIT as e:
            raise UserError(f"cannot resume: {path} does not fit this run ({ckpt.misfit_reason(e)})") from None

    # ------------------------------------------------------------------ events
    def _emit(self, name: str, event) -> None:
        for obs in list(self._observers):
            try:
                getattr(obs, name)(event)
            except Exception as e:  # observers never break training
                log.warning("observer %s.%s failed: %s: %s", type(obs).__name__, name, type(e).__name__, e)

    def _images_event(self, test_renders: list[dict[str, np.ndarray]] | None = None) -> ImagesEvent:
        """Test views and mirrored views with the current field (`test_renders`: render_tests(), if made)."""
        mirrors = list(zip(self.training.mirror_views, self.flip.mirror_cameras()))
        n = len(mirrors) + (0 if test_renders is not None else len(self.split.tests))
        render = self._evaluation(f"step {self.step}: rendering the test and mirrored views", n)
        return ev.images_event(self.step, render, self.split.tests, mirrors, test_renders)
