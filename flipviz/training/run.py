"""One training run, blocking: how the CLI, the bench and the studies make a Trainer and train it."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path

from flipviz.data.dataset import SceneData
from flipviz.training.checkpoint import CHECKPOINT_NAME
from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer
from flipviz.training.trainer import Trainer

log = logging.getLogger("flipviz.training")


def make_trainer(
    cfg: TrainConfig,
    scene: SceneData | None = None,
    resume_unfinished: bool = False,
    on_phase: Callable[[str], None] | None = None,
) -> Trainer:
    """A Trainer for `cfg` (`on_phase`: Trainer's). With `resume_unfinished` (the bench, whose run folders
    are its own), a run folder that already holds a checkpoint (a run that was killed) resumes from it, and
    any other (an unreadable checkpoint, a failed run's leftovers) starts over in place."""
    if not resume_unfinished or cfg.output.resume is not None:
        return Trainer(cfg, scene, on_phase)
    ckpt = Path(cfg.output.out) / CHECKPOINT_NAME if cfg.output.out is not None else None
    if ckpt is not None and ckpt.is_file():
        try:
            return Trainer(cfg.with_settings(resume=ckpt), scene, on_phase)
        except Exception as e:
            log.warning("cannot resume from %s (%s: %s); starting over", ckpt, type(e).__name__, e)
    return Trainer(cfg.with_settings(overwrite=True), scene, on_phase)


def train(
    cfg: TrainConfig, observers: Iterable[Observer] = (), resume_unfinished: bool = False
) -> tuple[Trainer, dict]:
    """Train one run to the end (Ctrl-C stops it gracefully); returns the trainer and its final metrics."""
    trainer = make_trainer(cfg, resume_unfinished=resume_unfinished)
    for obs in observers:
        trainer.add_observer(obs)
    return trainer, trainer.run()  # KeyboardInterrupt inside the loop ends it with status "stopped"
