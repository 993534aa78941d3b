"""One training run, blocking: how the CLI, the bench and the benchmarks make a Trainer and train it."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from dataclasses import fields, replace
from pathlib import Path

from flipviz.data.dataset import SceneData
from flipviz.errors import UserError
from flipviz.training.checkpoint import CHECKPOINT_NAME, checkpoint_path, load_checkpoint
from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer
from flipviz.training.trainer import Trainer

log = logging.getLogger("flipviz.training")


def make_trainer(cfg: TrainConfig, scene: SceneData | None = None, resume_unfinished: bool = False) -> Trainer:
    """A Trainer for `cfg`. With `resume_unfinished` (the bench, whose run folders are its own), a
    run folder that already holds a checkpoint (a run that was killed) resumes from it, and any other
    (an unreadable checkpoint, a failed run's leftovers) starts over in place."""
    if not resume_unfinished or cfg.resume is not None:
        return Trainer(cfg, scene)
    ckpt = Path(cfg.out) / CHECKPOINT_NAME if cfg.out is not None else None
    if ckpt is not None and ckpt.is_file():
        try:
            return Trainer(replace(cfg, resume=ckpt), scene)
        except Exception as e:
            log.warning("cannot resume from %s (%s: %s); starting over", ckpt, type(e).__name__, e)
    return Trainer(replace(cfg, overwrite=True), scene)


def train(
    cfg: TrainConfig, observers: Iterable[Observer] = (), resume_unfinished: bool = False
) -> tuple[Trainer, dict]:
    """Train one run to the end (Ctrl-C stops it gracefully); returns the trainer and its final metrics."""
    trainer = make_trainer(cfg, resume_unfinished=resume_unfinished)
    for obs in observers:
        trainer.add_observer(obs)
    return trainer, trainer.run()  # KeyboardInterrupt inside the loop ends it with status "stopped"


def run_config(settings: dict) -> TrainConfig:
    """A run's TrainConfig from its settings as saved (checkpoint["config"], metrics.json's "settings");
    settings that are not a TrainConfig's (a crafted or damaged file) are one UserError line."""
    if not isinstance(settings, dict):
        raise UserError(f"the run's saved settings are a {type(settings).__name__}, not a table")
    names = {f.name for f in fields(TrainConfig)}
    kw = {k: v for k, v in settings.items() if k in names}
    kw.setdefault("unconfident_plane", "use")  # saved before the option existed: any plane was trained with
    try:
        for k in ("data", "out", "rrd", "resume", "plane_file"):
            if kw.get(k) is not None:
                kw[k] = Path(kw[k])
        if kw.get("grid_res") is not None:
            kw["grid_res"] = tuple(kw["grid_res"])
        return TrainConfig(**kw)
    except (TypeError, ValueError) as e:
        raise UserError(f"the run's saved settings are damaged ({str(e).splitlines()[0][:120]})") from None


def open_run(run: Path | str, device: str | None = None, scene: SceneData | None = None) -> Trainer:
    """A run folder (or its checkpoint.pt) read back to render, as it was when it ended: its config,
    its scene, its model and its refined poses. Nothing in the folder is written or locked, so a run
    that another process is training can be opened too (at its last checkpoint)."""
    try:
        path = checkpoint_path(run)
    except FileNotFoundError:
        raise UserError(
            f"{run} is not a run folder with a checkpoint (bench runs keep theirs with --keep-checkpoints)"
        ) from None
    cfg = run_config(load_checkpoint(path).get("config"))
    cfg = replace(cfg, resume=path, out=path.parent, device=device or cfg.device, no_rrd=True).validate()
    if cfg.data is not None and not os.path.exists(cfg.data):  # False for a name the system refuses
        raise UserError(f"{path.parent} was trained on {cfg.data}, which is not found from here")
    return Trainer(cfg, scene, read_only=True)
