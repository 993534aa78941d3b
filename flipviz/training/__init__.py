"""Training layer: the five methods, the trainer loop with events, checkpoints, evaluation.

`Trainer` and `train` are imported lazily so that `flipviz.training.events` / `.config` stay
cheap to import for observers.
"""

from flipviz.training.config import METHODS, TrainConfig

__all__ = ["METHODS", "TrainConfig", "Trainer", "train"]


def __getattr__(name: str):
    if name == "Trainer":
        from flipviz.training.trainer import Trainer

        return Trainer
    if name == "train":
        from flipviz.training.run import train

        return train
    raise AttributeError(name)
