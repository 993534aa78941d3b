"""A run read back from its folder to look at (`flipviz report`, `video`, the app's Compare B): a small
record of its config, scene and views, its model and its mirrored cameras at their refined poses, as
its last checkpoint holds them. Nothing is trained, written or locked, and no Trainer is built: no
ray bank, no optimiser, no plane estimate (the run's own plane.json is read back).

    run = open_run("runs/chair-flip+u-1-...")    # checkpoint.pt -> config, scene, split, model
    out = run.render(camera)                      # rgb (H, W, 3), depth, opacity, beta2 (H, W)
    run.mirror_cameras()                          # the mirrored training cameras, BA-refined
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from flipviz.data.cameras import Camera
from flipviz.data.dataset import SceneData
from flipviz.data.protocol import Split
from flipviz.errors import UserError
from flipviz.files import inside_roots
from flipviz.model import RadianceModel
from flipviz.training import flip
from flipviz.training.artifacts import PLANE_FILE
from flipviz.training.checkpoint import MISFIT, checkpoint_path, counter, load_checkpoint, misfit_reason
from flipviz.training.config import TrainConfig
from flipviz.training.evaluate import score_renders
from flipviz.training.events import SetupEvent
from flipviz.training.methods import TrainView, method_spec
from flipviz.training.plane_estimate import read_estimate
from flipviz.training.pose_tuning import eval_renders, test_alignment
from flipviz.training.setup import evaluation_views, fresh_model, load_scene_for, run_split, setup_event


@dataclass
class Run:
    """A finished (or checkpointed) run, opened to render."""

    run_dir: Path
    cfg: TrainConfig
    scene: SceneData
    split: Split
    model: RadianceModel
    mirror_views: list[TrainView]  # the flipped inputs it trained on (empty: none)
    mirror_poses: np.ndarray | None  # (M, 4, 4) their poses at the checkpoint: the plane and BA applied
    step: int
    train_seconds: float
    setup_event: SetupEvent
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)  # one render at a time

    @torch.no_grad()
    def render(self, camera: Camera, outputs=("rgb", "depth", "opacity", "beta2")) -> dict[str, np.ndarray]:
        """A full image from `camera` with the run's model; thread-safe."""
        with self._lock:
            out = self.model.render_image(camera)
        return {k: out[k] for k in outputs if k in out}

    def mirror_c2w(self) -> np.ndarray | None:
        """(M, 4, 4) the mirrored training cameras' refined poses; None when the run trained none."""
        return self.mirror_poses

    def mirror_cameras(self) -> list[Camera]:
        """The mirrored training cameras at their refined poses."""
        poses = [] if self.mirror_poses is None else self.mirror_poses
        return [v.camera.with_pose(p) for v, p in zip(self.mirror_views, poses)]


def score(run: Run, views: str, tune_steps: int, every: int = 1) -> dict:
    """The run's scores under another protocol (EvalConfig: `views`, `tune_steps`) from its checkpoint: what
    `flipviz score` prints, e.g. a run of flipviz's protocol scored as the released code scores."""
    cfg = run.cfg.with_settings(eval_views=views, eval_tune_steps=tune_steps, eval_every=every).validate()
    tests = evaluation_views(cfg, run.scene, run.split)
    align = test_alignment(method_spec(cfg).refine_inputs, [v.camera for v in run.mirror_views], run.mirror_poses)
    renders = eval_renders(run.render, run.model, tests, tune_steps, align, cfg.engine.seed)
    out = score_renders(run.scene, tests, renders)
    protocol = {"eval_views": views, "eval_tune_steps": tune_steps, "eval_every": every}
    return out | protocol | {"scored_views": len(tests), "step": run.step}


def run_config(settings: dict) -> TrainConfig:
    """A run's TrainConfig from its settings as saved (checkpoint["config"], metrics.json's "settings");
    settings that are not a TrainConfig's (a crafted or damaged file) are one UserError line."""
    if not isinstance(settings, dict):
        raise UserError(f"the run's saved settings are a {type(settings).__name__}, not a table")
    names = set(TrainConfig().settings())
    kw = {k: v for k, v in settings.items() if k in names}
    kw.setdefault("unconfident_plane", "use")  # saved before the option existed: any plane was trained with
    kw.setdefault("mirror_disagreement_limit", float("inf"))  # saved before per-mirror verdicts: all or none
    try:
        for k in ("data", "out", "rrd", "resume", "plane_file"):
            if kw.get(k) is not None:
                kw[k] = Path(kw[k])
        if kw.get("grid_res") is not None:
            kw["grid_res"] = tuple(kw["grid_res"])
        return TrainConfig.from_settings(**kw)
    except (TypeError, ValueError) as e:
        raise UserError(f"the run's saved settings are damaged ({str(e).splitlines()[0][:120]})") from None


def open_run(
    run: Path | str, device: str | None = None, scene: SceneData | None = None, roots: list[Path] | None = None
) -> Run:
    """A run folder (or its checkpoint.pt) read back as it was at its last checkpoint. A run another
    process is training opens too (at its last checkpoint): nothing here writes or locks. `roots`: the
    folders a browser may make the server read (the app's browse roots); the dataset the run names
    must lie inside them, and a refusal never says whether a path outside them exists."""
    try:
        path = checkpoint_path(run)
    except FileNotFoundError:
        keep = "bench runs keep theirs with --keep-checkpoints"
        raise UserError(f"{run} is not a run folder with a checkpoint ({keep})") from None
    state = load_checkpoint(path)
    cfg = run_config(state.get("config"))
    # what the run wrote or read besides its dataset is never opened again (its --plane-file was read once)
    cfg = cfg.with_settings(
        resume=None, out=path.parent, rrd=None, plane_file=None, device=device or cfg.engine.device, no_rrd=True
    ).validate()
    if cfg.data.path is not None and roots is not None:
        inside_roots(cfg.data.path, roots, f"the dataset of {path.parent.name}")
    if cfg.data.path is not None and not os.path.exists(cfg.data.path):  # False for a name the system refuses
        raise UserError(f"{path.parent} was trained on {cfg.data.path}, which is not found from here")
    scene = scene if scene is not None else load_scene_for(cfg)
    split = run_split(cfg, scene)
    estimate = read_estimate(path.parent / PLANE_FILE)
    mirrors = flip.mirrored_views(cfg.flip, split.inputs, scene, estimate.plane if estimate else None)
    spec = method_spec(cfg)
    try:  # a crafted or foreign checkpoint fails in many ways below: each is one line
        poses = _mirror_poses(state, spec.mirrors, len(mirrors.views))
        if spec.mirrors and poses is None:  # dropped at setup: its plane was doubted (--unconfident-plane drop)
            spec = spec.without_mirrors()
        start, step = counter(state, "field_start", 0), counter(state, "step")
        restarted = start > 0 and cfg.flip.after_drop == "restart"  # a fresh field on the inputs: no beta head
        model = fresh_model(cfg, scene, with_beta=spec.uses_beta and not restarted)  # a rollback keeps it
        model.load_state_dict(state["model"])
        seconds = float(state.get("train_seconds", 0.0))
    except MISFIT as e:
        raise UserError(f"cannot open {path}: it does not fit its own run ({misfit_reason(e)})") from None
    views = flip.mirrored_train_views(spec, mirrors, scene.bbox) if poses is not None else []
    event = setup_event(path.parent.name, cfg, scene, split, mirrors, spec.mirrors, estimate)
    return Run(path.parent, cfg, scene, split, model, views, poses, step, seconds, event)


def _mirror_poses(state: dict, trained: bool, count: int) -> np.ndarray | None:
    """The checkpoint's (M, 4, 4) refined mirrored poses (None: the run trained no mirrored view)."""
    if "mirror_c2w" not in state:
        if not trained:
            return None
        raise ValueError("no mirrored poses: it was written before flipviz kept them; resume it once to add them")
    c2w = state["mirror_c2w"]
    if c2w is None:
        return None
    c2w = c2w.detach().cpu().double().numpy() if isinstance(c2w, torch.Tensor) else None
    if c2w is None or c2w.shape != (count, 4, 4) or not np.isfinite(c2w).all():
        raise ValueError(f"its mirrored poses are not {count} finite 4x4 poses")
    return c2w
