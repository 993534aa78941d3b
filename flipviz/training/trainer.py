"""The training loop of the five methods, with events, a thread-safe render, pause/resume/stop.

One step (paper Sec. IV-B/IV-C): draw `batch_rays` random rays from the ray bank, build their
origins/directions from the current poses (refined ones for mirrored cameras, so BA gets
gradients), volume-render them and minimise
    originals:                 ||C - C_hat||^2                                     (squared error)
    rays under uncertainty:    ||C - C_hat||^2 / (2 b^2) + log(b^2) / 2 + w/N_s sum_j sigma(t_j)
                               (paper Sec. IV-C, after the first `uncertainty_start` of the steps)
plus the field's regulariser. Field and pose optimisers step together.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import torch

from flipviz.data.cameras import Camera, rays_from_c2w
from flipviz.data.dataset import SceneData
from flipviz.data.protocol import make_split
from flipviz.geometry import fit_camera_sphere, make_mirror_set, pose_errors
from flipviz.model import PoseRefiner, RadianceModel, losses
from flipviz.training import checkpoint as ckpt
from flipviz.training import evaluate as ev
from flipviz.training.config import TrainConfig
from flipviz.training.events import (
    CameraInfo,
    EndEvent,
    ImagesEvent,
    Observer,
    RenderedView,
    SetupEvent,
    StepEvent,
)
from flipviz.training.methods import build_training_set, method_spec

log = logging.getLogger("flipviz.training")


class NonFiniteLoss(RuntimeError):
    pass


def scene_label(cfg: TrainConfig, scene: SceneData | None = None) -> str:
    if scene is not None:
        return scene.name
    return Path(cfg.data).name if cfg.data is not None else cfg.scene


def load_scene_for(cfg: TrainConfig) -> SceneData:
    """The scene of a run: a Blender folder (cfg.data) or a built-in scene, at cfg.res pixels."""
    from flipviz.data import load_scene

    return load_scene(cfg.scene, cfg.data, cfg.res)


def default_run_dir(cfg: TrainConfig, scene_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{scene_name}-{cfg.method}-{cfg.config}-{stamp}"


class Trainer:
    def __init__(self, cfg: TrainConfig, scene: SceneData | None = None) -> None:
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        self._gen = torch.Generator().manual_seed(cfg.seed)
        if scene is None:
            scene = load_scene_for(cfg)
        self.scene = scene
        self.split = make_split(scene, cfg.config)
        self.spec = method_spec(cfg)
        self.sphere = fit_camera_sphere([v.camera for v in self.split.inputs])
        # The mirrored set is built for every method so that the app can show the would-be mirrors;
        # only Flip methods train on it.
        self.mirror_set = make_mirror_set(self.split.inputs, cfg.mirror_plane, scene.symmetry_plane)
        self.ts = build_training_set(
            cfg, self.split.inputs, self.mirror_set.views, self.split.uppers, device=self.device
        )
        self.model = RadianceModel(
            _field_config(cfg), scene.bbox, scene.near, scene.far, with_beta=self.spec.uses_beta, device=self.device
        )
        self.refiner = (
            PoseRefiner(self.ts.init_c2w, self.ts.refine_mask, cfg.steps, device=self.device)
            if bool(self.ts.refine_mask.any())
            else None
        )
        self.opt_field = self.model.make_optimizer(cfg.steps)
        self.opt_pose = self.refiner.make_optimizer() if self.refiner is not None else None
        self.run_dir = Path(cfg.out) if cfg.out is not None else default_run_dir(cfg, scene.name)
        self.step = 0
        self.status = "created"
        self._observers: list[Observer] = []
        self._lock = threading.RLock()  # one lock for a training step and for render()
        self._running = threading.Event()
        self._running.set()  # set = not paused
        self._stop = threading.Event()
        self._t_train = 0.0  # seconds spent in training steps (excludes pauses and image renders)
        self.last_metrics: dict = {}
        if cfg.resume is not None:
            self._load(cfg.resume)
        self.setup_event = self._make_setup_event()

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

    def stop(self) -> None:
        self._stop.set()
        self._running.set()  # a paused loop must wake up to stop

    @torch.no_grad()
    def render(self, camera: Camera, outputs=("rgb", "depth", "opacity", "beta2")) -> dict[str, np.ndarray]:
        """Render a full image from `camera` with the current field; thread-safe."""
        with self._lock:
            out = self.model.render_image(camera)
        return {k: out[k] for k in outputs if k in out and out[k] is not None}

    # ------------------------------------------------------------------ poses
    def current_poses(self) -> torch.Tensor:
        """(V, 4, 4) current poses of all training views (refined where BA is on)."""
        return self.refiner() if self.refiner is not None else self.ts.init_c2w

    def mirror_c2w(self) -> np.ndarray | None:
        if not self.ts.mirror_ids:
            return None
        with torch.no_grad():
            return self.current_poses()[self.ts.mirror_ids].detach().cpu().double().numpy()

    def mirror_cameras(self) -> list[Camera]:
        """The mirrored training cameras at their current (refined) poses."""
        c2w = self.mirror_c2w()
        if c2w is None:
            return []
        return [v.camera.with_pose(p) for v, p in zip(self.ts.mirror_views, c2w)]

    # ------------------------------------------------------------------ events
    def _emit(self, name: str, event) -> None:
        for obs in list(self._observers):
            try:
                getattr(obs, name)(event)
            except Exception as e:  # observers never break training
                log.warning("observer %s.%s failed: %s: %s", type(obs).__name__, name, type(e).__name__, e)

    def _make_setup_event(self) -> SetupEvent:
        cams = [CameraInfo("input", v.camera, v.rgb, v.name) for v in self.split.inputs]
        ms = self.mirror_set
        for v in ms.views:
            cams.append(CameraInfo("mirror_init", v.camera, v.rgb, v.meta.get("source", "")))
        for c, v in zip(ms.true_cameras or [], self.split.inputs):
            cams.append(CameraInfo("mirror_true", c, None, v.name))
        cams += [CameraInfo("test", v.camera, v.rgb, v.name) for v in self.split.tests]
        cams += [CameraInfo("upper", v.camera, v.rgb, v.name) for v in self.split.uppers]
        return SetupEvent(
            run_name=self.run_dir.name,
            scene=self.scene.name,
            method=self.cfg.method,
            config=self.cfg.config,
            total_steps=self.cfg.steps,
            sphere_center=ms.sphere.center.copy(),
            sphere_radius=float(ms.sphere.radius),
            plane=ms.plane if self.spec.mirrors else None,
            true_plane=self.scene.symmetry_plane,
            cameras=cams,
            bbox=np.asarray(self.scene.bbox, dtype=np.float64),
            settings=self.cfg.to_dict(),
        )

    def _pose_report(self) -> dict:
        c2w = self.mirror_c2w()
        if c2w is None:
            return {}
        init = [v.camera.c2w for v in self.ts.mirror_views]
        change = np.array([pose_errors(a, b) for a, b in zip(c2w, init)])
        rep = dict(mirror_c2w=c2w, mirror_rot_change_deg=change[:, 0], mirror_trans_change=change[:, 1])
        if self.mirror_set.true_cameras is not None:
            err = np.array([pose_errors(a, t.c2w) for a, t in zip(c2w, self.mirror_set.true_cameras)])
            rep.update(mirror_rot_err_deg=err[:, 0], mirror_trans_err=err[:, 1])
        return rep

    def _images_event(self) -> ImagesEvent:
        tests, mirrors = [], []
        for v in self.split.tests:
            r = self.render(v.camera)
            tests.append(RenderedView(v.name, "test", v.camera, r["rgb"], r["depth"], r["opacity"], r.get("beta2"), v.rgb))
        for tv, cam in zip(self.ts.mirror_views, self.mirror_cameras()):
            r = self.render(cam)
            mirrors.append(
                RenderedView(cam.name, "mirror_init", cam, r["rgb"], r["depth"], r["opacity"], r.get("beta2"), tv.image)
            )
        scalars = {"test_psnr": float(np.mean([ev.psnr(t.rgb, t.gt) for t in tests]))} if tests else {}
        return ImagesEvent(self.step, tests, mirrors, scalars)

    # ------------------------------------------------------------------ one step
    def uses_nll(self, step: int | None = None) -> bool:
        """The uncertainty loss is on after the first `uncertainty_start` of training (paper: 10k of 50k)."""
        step = self.step if step is None else step
        return self.spec.uses_beta and step >= int(self.cfg.uncertainty_start * self.cfg.steps)

    def _loss(self, out: dict, target: torch.Tensor, uncertain: torch.Tensor) -> torch.Tensor:
        """Mean over the batch of the per-ray losses of the module docstring.

        Under uncertainty, rays without it have beta_hat^2 = beta_min^2 (paper Sec. IV-C), so their
        NLL is ||C - C_hat||^2 / (2 beta_min^2) + const. The whole loss is scaled by the constant
        2 beta_min^2 / 3: those rays then contribute exactly their MSE, as in the warm-up phase.
        """
        sq = ((out["rgb"] - target) ** 2).sum(-1)  # ||C - C_hat||^2 per ray
        if not self.uses_nll() or not bool(uncertain.any()):
            return sq.mean() / 3.0  # photometric MSE over rays and channels
        u, n = uncertain, sq.shape[0]
        b2min = self.model.cfg.beta_min**2
        # paper Sec. IV-C: L(r') = ||C - C_hat||^2 / (2 beta^2) + log(beta^2) / 2 + w / N_s sum_j sigma(t_j)
        nll = losses.uncertainty_nll(
            out["rgb"][u], target[u], out["beta2"][u], out["sigma_mean"][u], self.cfg.density_weight
        )
        certain = sq[~u].sum() / (2.0 * b2min) if bool((~u).any()) else sq.new_zeros(())
        return (2.0 * b2min / 3.0) * (nll * int(u.sum()) + certain) / n

    def _train_step(self) -> dict:
        cfg, bank = self.cfg, self.ts.bank
        if self.model.update_schedule(self.step, cfg.steps):  # grids upsampled: new parameters
            self.opt_field = self.model.make_optimizer(cfg.steps)
        self.model.adjust_lr(self.opt_field, self.step, cfg.steps)
        if self.refiner is not None:
            self.refiner.adjust_lr(self.opt_pose, self.step)
        idx = bank.sample(self.cfg.batch_rays, self._gen)
        poses = self.current_poses()
        o, d = rays_from_c2w(poses[bank.cam[idx]], bank.dirs_cam[idx])
        out = self.model.render_rays(o, d, training=True)
        target = bank.rgb[idx]
        loss = self._loss(out, target, bank.uncertain[idx])
        reg = self.model.regulariser()
        total = loss + reg if reg is not None else loss
        if not torch.isfinite(total):
            raise NonFiniteLoss(f"loss became {float(total.detach())} at step {self.step + 1}")
        self.opt_field.zero_grad(set_to_none=True)
        if self.opt_pose is not None:
            self.opt_pose.zero_grad(set_to_none=True)
        total.backward()
        self.opt_field.step()
        if self.opt_pose is not None:
            self.opt_pose.step()
        with torch.no_grad():
            mse = float(((out["rgb"] - target) ** 2).mean())
        self.step += 1
        return {
            "loss": float(total.detach()),
            "psnr": -10.0 * math.log10(max(mse, 1e-12)),
            "lr_field": float(self.opt_field.param_groups[0]["lr"]),
            "lr_pose": float(self.opt_pose.param_groups[0]["lr"]) if self.opt_pose is not None else 0.0,
        }

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "config": self.cfg.to_dict(),
            "model": self.model.state_dict(),
            "poses": self.refiner.state_dict() if self.refiner is not None else None,
            "opt_field": self.opt_field.state_dict(),
            "opt_pose": self.opt_pose.state_dict() if self.opt_pose is not None else None,
            "train_seconds": self._t_train,
            "rng": self._gen.get_state(),
            "torch_rng": torch.get_rng_state(),
        }

    def save_checkpoint(self) -> Path | None:
        """Write checkpoint.pt (atomically), unless the state is not finite (keeps the last good one)."""
        with self._lock:
            state = self.checkpoint_state()
            if not (ckpt.state_is_finite(state["model"]) and ckpt.state_is_finite(state["poses"] or {})):
                log.warning("not saving a non-finite state at step %d; the last good checkpoint is kept", self.step)
                return None
            return ckpt.save_checkpoint(self.run_dir / ckpt.CHECKPOINT_NAME, state)

    def _load(self, path: Path | str) -> None:
        state = ckpt.load_checkpoint(path, map_location=self.device)
        self.model.load_state_dict(state["model"])
        self.opt_field = self.model.make_optimizer(self.cfg.steps)
        self.opt_field.load_state_dict(state["opt_field"])
        if self.refiner is not None and state.get("poses") is not None:
            self.refiner.load_state_dict(state["poses"])
            self.opt_pose = self.refiner.make_optimizer()
            if state.get("opt_pose") is not None:
                self.opt_pose.load_state_dict(state["opt_pose"])
        self.step = int(state["step"])
        self._t_train = float(state.get("train_seconds", 0.0))
        if state.get("rng") is not None:
            self._gen.set_state(state["rng"])
        if state.get("torch_rng") is not None:
            torch.set_rng_state(state["torch_rng"])

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, write: bool = True) -> dict:
        """Score the 8 unobserved test views; write metrics.json, test_renders/, transforms.json."""
        preds = [self.render(v.camera, ("rgb",))["rgb"] for v in self.split.tests]
        m = ev.score_views(preds, [v.rgb for v in self.split.tests], [v.name for v in self.split.tests])
        m.update(
            train_seconds=self._t_train,
            steps=self.step,
            method=self.cfg.method,
            config=self.cfg.config,
            scene=self.scene.name,
            mirror_plane=self.cfg.mirror_plane,
            settings=self.cfg.to_dict(),
        )
        pose = self._pose_report()
        if pose:
            m["mirror_poses"] = {k: np.asarray(v).tolist() for k, v in pose.items()}
        if write:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            for v, p in zip(self.split.tests, preds):
                ev.save_png(self.run_dir / "test_renders" / f"{v.name}.png", p)
                ev.save_png(self.run_dir / "test_renders" / f"{v.name}_gt.png", v.rgb)
            if self.ts.mirror_ids:
                cams = self.mirror_cameras()
                ev.export_transforms(self.run_dir / "transforms.json", cams, [tv.image for tv in self.ts.mirror_views])
            ev.write_json(self.run_dir / "metrics.json", m)
        self.last_metrics = m
        return m

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict:
        """Train to cfg.steps (or until stopped / NaN); returns the final metrics."""
        cfg = self.cfg
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.status = "running"
        self._emit("on_setup", self.setup_event)
        status, message = "finished", ""
        try:
            while self.step < cfg.steps:
                if not self._running.is_set():
                    self._running.wait()  # paused: block between steps, without the render lock
                if self._stop.is_set():
                    status = "stopped"
                    break
                t0 = time.perf_counter()
                with self._lock:
                    scalars = self._train_step()
                self._t_train += time.perf_counter() - t0
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    self._emit("on_step", StepEvent(self.step, cfg.steps, self._t_train, scalars, **self._pose_report()))
                if cfg.images_every > 0 and self.step % cfg.images_every == 0 and self.step < cfg.steps:
                    self._emit("on_images", self._images_event())
                if cfg.checkpoint_every > 0 and self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
        except NonFiniteLoss as e:
            status, message = "nan", f"{e}; stopped, last good checkpoint kept in {self.run_dir}"
            log.error("%s", message)
        except KeyboardInterrupt:
            status, message = "stopped", "interrupted"
        except Exception as e:
            status, message = "error", f"{type(e).__name__}: {e}"
            log.exception("training failed")
        self.status = status
        metrics: dict = {}
        if status in ("finished", "stopped"):
            self.save_checkpoint()
            if status == "finished" or cfg.eval_on_stop:
                try:
                    metrics = self.evaluate()
                    self._emit("on_images", self._images_event())
                except KeyboardInterrupt:  # a second Ctrl-C skips the evaluation, keeps the checkpoint
                    status = "stopped"
                    message = f"interrupted during the final evaluation; checkpoint kept in {self.run_dir}"
                    metrics = {}
        metrics = dict(metrics, status=status, message=message, steps=self.step, run_dir=str(self.run_dir))
        self.last_metrics = metrics
        self._emit("on_end", EndEvent(self.step, status, message, metrics))
        return metrics


def _field_config(cfg: TrainConfig):
    """The model's FieldConfig for this run."""
    from flipviz.model import FieldConfig

    fc = FieldConfig(kind=cfg.field, beta2_mode=cfg.beta2_mode)
    if cfg.n_samples is not None:
        fc.n_samples = int(cfg.n_samples)
    if cfg.grid_res is not None:
        fc.grid_res = tuple(int(r) for r in cfg.grid_res)
        n_up = len(fc.grid_res) - 1  # upsample at evenly spread fractions of the first half
        fc.upsample_at = tuple(0.5 * (i + 1) / (n_up + 1) for i in range(n_up))
    if cfg.field == "nerf" and cfg.ba and cfg.method in ("flip", "flip+u"):
        fc.nerf_barf_c2f = (0.1, 0.5)  # BARF's coarse-to-fine positional encoding
    return fc
