"""One training run, blocking: the one way the CLI, the bench and the benchmarks train."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Iterable

from flipviz.data.dataset import SceneData
from flipviz.training.checkpoint import CHECKPOINT_NAME
from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer
from flipviz.training.trainer import Trainer

log = logging.getLogger("flipviz.training")


def make_trainer(cfg: TrainConfig, scene: SceneData | None = None, resume_unfinished: bool = False) -> Trainer:
    """A Trainer for `cfg`. With `resume_unfinished`, a run folder that already holds a checkpoint
    (a run that was killed) resumes from it; an unreadable checkpoint starts over."""
    ckpt = Path(cfg.out) / CHECKPOINT_NAME if cfg.out is not None else None
    if resume_unfinished and cfg.resume is None and ckpt is not None and ckpt.is_file():
        try:
            return Trainer(replace(cfg, resume=ckpt), scene)
        except Exception as e:
            log.warning("cannot resume from %s (%s: %s); starting over", ckpt, type(e).__name__, e)
    return Trainer(cfg, scene)


def train(cfg: TrainConfig, observers: Iterable[Observer] = (), resume_unfinished: bool = False) -> tuple[Trainer, dict]:
    """Train one run to the end (Ctrl-C stops it gracefully); returns the trainer and its final metrics."""
    trainer = make_trainer(cfg, resume_unfinished=resume_unfinished)
    for obs in observers:
        trainer.add_observer(obs)
    return trainer, trainer.run()  # KeyboardInterrupt inside the loop ends it with status "stopped"
