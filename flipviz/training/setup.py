"""Everything a run trains with, built once from its config and scene, in the paper's order.

split      = the protocol's inputs / unobserved tests / Upper views     (data/protocol.py),
             or a capture's chosen inputs and held-out frames            (data/selection.py)
estimate   = with --mirror-plane auto, the plane estimated from inputs  (plane_estimate.py):
             from the run's own field after its input-only steps (the trainer builds the run
             again then, keeping the field), or from a separate fit (--estimate-after 0);
             not confident: no mirrored view is trained on (--unconfident-plane drop);
             mirrors that are trained and disagree with the inputs are dropped later
             (flip.py: the agreement gate)
mirrors    = flipped inputs with their initial poses                    (flip.py, step 1)
training   = the method's views and their ray bank                      (methods.py)
model      = radiance field + renderer                                  (model/radiance.py)
flip       = what Just Flip moves and how it scores a batch             (flip.py: the plane,
             BA of the mirrored poses, MSE then the NLL on uncertain rays)
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from flipviz.data.cameras import View
from flipviz.data.dataset import SceneData, check_image_size
from flipviz.data.protocol import TURN, Split, make_split
from flipviz.data.selection import select_split
from flipviz.errors import UserError
from flipviz.geometry.mirror import MirrorSet
from flipviz.geometry.symmetry import PlaneEstimate
from flipviz.model import GridConfig, ModelConfig, NerfConfig, RadianceModel
from flipviz.training import flip
from flipviz.training.config import TrainConfig
from flipviz.training.events import CameraInfo, SetupEvent
from flipviz.training.methods import MethodSpec, TrainingSet, build_training_set, method_spec
from flipviz.training.plane_estimate import (
    estimate_from_field,
    estimate_or_read,
    estimate_plane,
    read_estimate,
    shared_estimate,
)

log = logging.getLogger("flipviz.training")


@dataclass
class RunSetup:
    scene: SceneData
    spec: MethodSpec  # without mirrors when an unconfident plane was dropped (cfg.method still names the method)
    split: Split
    mirrors: MirrorSet  # built for every method, so that the app can show the would-be mirrors
    estimate: PlaneEstimate | None  # --mirror-plane auto (Flip methods)
    training: TrainingSet
    model: RadianceModel
    flip: flip.Flip
    start_over: bool = False  # built again after the warm-up without mirrors: the run starts afresh as B/L


def model_config(cfg: TrainConfig) -> ModelConfig:
    """The model of a run: the field's defaults, with the run's samples and grid resolutions."""
    field: GridConfig | NerfConfig
    if cfg.engine.field == "nerf":
        ba = cfg.flip.ba and cfg.method in ("flip", "flip+u")
        c2f = (0.1, 0.5) if ba else None  # BARF's coarse-to-fine PE with BA
        field = NerfConfig(barf_c2f=c2f)
    elif cfg.engine.grid_res is not None:
        n_up = len(cfg.engine.grid_res) - 1  # upsample at evenly spread fractions of the first half
        field = GridConfig(
            grid_res=tuple(cfg.engine.grid_res), upsample_at=tuple(0.5 * (i + 1) / (n_up + 1) for i in range(n_up))
        )
    else:
        field = GridConfig()
    if cfg.engine.lr_end is not None:
        field = replace(field, lr_decay=cfg.engine.lr_end)
    return ModelConfig(
        field=field,
        w_entropy=cfg.engine.entropy_weight,
        n_samples=cfg.engine.n_samples,
        beta2_mode=cfg.flip.beta2_mode,
        background=cfg.engine.background,
        beta_from=cfg.flip.beta_from,
    )


def fresh_model(cfg: TrainConfig, scene: SceneData, with_beta: bool) -> RadianceModel:
    """A newly initialised model of the run (the agreement gate's restart builds one mid-run)."""
    return RadianceModel(
        model_config(cfg),
        scene.bbox,
        scene.near,
        scene.far,
        with_beta=with_beta,
        device=torch.device(cfg.engine.device),
    )


def load_scene_for(cfg: TrainConfig) -> SceneData:
    """The scene of a run: a Blender folder (cfg.data.path) or a built-in scene, at cfg.data.res pixels."""
    from flipviz.data import load_scene

    return load_scene(cfg.data.scene, cfg.data.path, cfg.data.res)


def evaluation_views(cfg: TrainConfig, scene: SceneData, split: Split) -> list[View]:
    """The views a run is scored on (cfg.eval.eval_views): the protocol's unobserved views, or every view of
    the orbit the run did not train on (a built-in's first turn is rendered for it); a capture's held-out
    frames either way. Every n-th of them (cfg.eval.eval_every)."""
    if cfg.eval.eval_views == "unobserved" or not scene.protocol:
        return split.tests[:: cfg.eval.eval_every]
    trained = {v.index for v in split.inputs} | ({v.index for v in split.uppers} if cfg.method == "upper" else set())
    orbit = scene.views
    if cfg.data.path is None:  # a built-in holds the protocol's views: render its whole first turn
        from flipviz.data import load_builtin

        orbit = load_builtin(scene.name, cfg.data.res, indices=range(TURN)).views
    return [v for i, v in sorted(orbit.items()) if i not in trained][:: cfg.eval.eval_every]


def run_split(cfg: TrainConfig, scene: SceneData) -> Split:
    """The protocol's configuration for orbit data without --inputs; else the chosen inputs."""
    if scene.protocol and not cfg.data.inputs:
        return make_split(scene, cfg.data.config)
    if cfg.method == "upper":
        raise UserError("method upper needs the protocol's Upper views: an orbit scene without --inputs")
    return select_split(scene, cfg.data.inputs)


def mirrors_join_at(cfg: TrainConfig) -> int:
    """The step the mirrored views join: with --mirror-plane auto on the grid field, after --estimate-after
    steps on the inputs alone when they fit in the first quarter of the run; else 0 (the mirrors train
    from the start; auto's plane then comes from a separate fit, as a younger field's would be doubted)."""
    if cfg.flip.mirror_plane != "auto" or cfg.engine.field == "nerf" or cfg.flip.estimate_after > cfg.engine.steps // 4:
        return 0
    return cfg.flip.estimate_after


def build_run(
    cfg: TrainConfig,
    scene: SceneData,
    saved_estimate: Path | None = None,
    estimate: PlaneEstimate | None = None,
    model: RadianceModel | None = None,
    say: Callable[[str], None] = lambda _: None,
) -> RunSetup:
    """Everything a run trains with. `saved_estimate`: the plane.json of a run being resumed; `estimate`:
    auto's plane, estimated from the run's own `model` after its input-only steps (that field trains on);
    `say`: hears what takes long (Trainer's on_phase)."""
    check_image_size(*scene.resolution, f"the images of {scene.source or scene.name}")
    device = torch.device(cfg.engine.device)
    spec = method_spec(cfg)
    split = run_split(cfg, scene)
    warm_up, with_beta = 0, spec.uses_beta
    if cfg.flip.mirror_plane == "auto" and spec.mirrors and estimate is None:
        if mirrors_join_at(cfg) > 0:  # read back (a resumed run's), else estimated from this run's field later
            estimate = read_estimate(saved_estimate)
            warm_up = mirrors_join_at(cfg) if estimate is None else 0
        else:
            say("estimating the mirror plane: a short fit of the inputs, then the search (10-20 s on 2 cores)")
            estimate = estimate_or_read(
                split.inputs, scene, cfg.engine.device, cfg.engine.seed, saved_estimate, cfg.flip.plane_file
            )
    if warm_up:  # the inputs alone until the estimate; the field has what the run needs after it
        spec = spec.without_mirrors()
    elif estimate is not None:
        if not estimate.confident and cfg.flip.unconfident_plane == "drop":
            log.warning(
                "training without the mirrored views: the plane is not confident (--unconfident-plane use keeps them)"
            )
            spec = spec.without_mirrors()
            with_beta = spec.uses_beta
        elif not estimate.confident:
            log.warning(
                "the plane is not confident: its mirrored views train while they agree with the inputs "
                "(--disagreement-limit; --unconfident-plane drop trains without them)"
            )
    mirrors = flip.mirrored_views(cfg.flip, split.inputs, scene, estimate.plane if estimate else None)
    training = build_training_set(
        spec, split.inputs, flip.mirrored_train_views(spec, mirrors, scene.bbox), split.uppers, device=device
    )
    start_over = model is not None and not spec.mirrors  # dropped for its confidence after the warm-up
    model = model if model is not None else fresh_model(cfg, scene, with_beta)
    join = mirrors_join_at(cfg) if spec.mirrors else 0
    hooks = flip.Flip(
        cfg.flip,
        cfg.engine.steps,
        training,
        mirrors,
        spec.mirrors,
        model.cfg.beta_min,
        device,
        start=join,
        warm_up=warm_up,
        estimate=estimate,
        true_plane=scene.symmetry_plane,
    )
    return RunSetup(scene, spec, split, mirrors, estimate, training, model, hooks, start_over)


def join_mirrors(cfg: TrainConfig, scene: SceneData, model: RadianceModel, steps: int) -> RunSetup:
    """--mirror-plane auto, after `steps` steps of `model` on the inputs alone: the plane estimated from
    that field (plane_estimate.py; or read from --plane-file, another run's), and the run built again
    around the same field with its mirrored views. A doubted plane under --unconfident-plane drop gives a
    run without them (`start_over`: it trains afresh as B/L; the bench then takes B/L's result)."""
    split = run_split(cfg, scene)
    shared = Path(cfg.flip.plane_file) if cfg.flip.plane_file is not None else None
    est = read_estimate(shared)
    if est is None:
        try:
            est = estimate_from_field(model, split.inputs, scene, cfg.engine.seed, steps)
        except ValueError as e:  # too few steps to show a surface yet
            log.warning("%s after %d steps; estimating it with a separate fit instead", e, steps)
            est = estimate_plane(split.inputs, scene, cfg.engine.device, cfg.engine.seed)
        est = shared_estimate(est, shared)
    return build_run(cfg, scene, estimate=est, model=model)


def setup_event(
    run_name: str,
    cfg: TrainConfig,
    scene: SceneData,
    split: Split,
    mirrors: MirrorSet,
    trained: bool,
    estimate: PlaneEstimate | None,
) -> SetupEvent:
    """What a run is made of, for its observers and viewers: its cameras with their images, the
    mirrors' sphere and plane (`trained`: the mirrored views are trained on), the scene's box and up."""
    cams = [CameraInfo("input", v.camera, v.rgb, v.name) for v in split.inputs]
    cams += [CameraInfo("mirror_init", v.camera, v.rgb, v.meta.get("source", "")) for v in mirrors.views]
    cams += [CameraInfo("mirror_true", c, None, v.name) for c, v in zip(mirrors.true_cameras or [], split.inputs)]
    cams += [CameraInfo("test", v.camera, v.rgb, v.name, v.alpha) for v in split.tests]
    cams += [CameraInfo("upper", v.camera, v.rgb, v.name) for v in split.uppers]
    return SetupEvent(
        run_name=run_name,
        scene=scene.name,
        method=cfg.method,
        config=split.config,
        total_steps=cfg.engine.steps,
        sphere_center=mirrors.sphere.center.copy(),
        sphere_radius=float(mirrors.sphere.radius),
        plane=mirrors.plane if trained else None,
        true_plane=scene.symmetry_plane,
        cameras=cams,
        bbox=np.asarray(scene.bbox, dtype=np.float64),
        cfg=cfg,
        near=float(scene.near),
        far=float(scene.far),
        up=np.asarray(scene.up, dtype=np.float64),
        plane_estimate=estimate,
    )
