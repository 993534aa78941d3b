"""`flipviz train`: build a Trainer, show a progress bar, run, return the metrics."""

from __future__ import annotations

import logging
from typing import Iterable

from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer
from flipviz.training.progress import ProgressObserver
from flipviz.training.trainer import Trainer


def train(cfg: TrainConfig, extra_observers: Iterable[Observer] = (), progress: bool = True) -> dict:
    """Train one run (blocking). Ctrl-C stops gracefully: the checkpoint is kept (and evaluated)."""
    logging.basicConfig(level=logging.WARNING, format="[flipviz] %(message)s")
    trainer = Trainer(cfg)
    if progress:
        trainer.add_observer(ProgressObserver())
    for obs in extra_observers:
        trainer.add_observer(obs)
    # The trainer catches KeyboardInterrupt raised inside its loop and ends with status "stopped".
    metrics = trainer.run()
    print(f"[flipviz] run folder: {trainer.run_dir}")
    if "psnr" in metrics:
        lp = metrics.get("lpips")
        lp_s = f"{lp:.3f}" if isinstance(lp, float) else f"{lp} ({metrics.get('lpips_reason', '')})"
        print(
            f"[flipviz] {metrics['status']}: unobserved views PSNR {metrics['psnr']:.2f} dB, "
            f"SSIM {metrics['ssim']:.3f}, LPIPS {lp_s}, {metrics.get('train_seconds', 0):.0f} s, {metrics['steps']} steps"
        )
    elif metrics.get("message"):
        print(f"[flipviz] {metrics['status']}: {metrics['message']}")
    return metrics
