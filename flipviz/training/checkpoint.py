"""Checkpoints: field + poses + config + step + optimiser states, written atomically.

A checkpoint is only ever written from a finite training state, and always through a temporary
file renamed over the old one, so the file on disk is the last good state even if the process
dies or the loss turns NaN.

Opening a checkpoint never runs code: it is read with torch's weights-only unpickler, which
builds tensors, numbers, strings and plain containers and refuses anything else (a pickle can
name any Python callable, and runs it when loaded). Runs are shared with a class and between
researchers; a folder someone hands you is data, not a program. Every checkpoint flipviz has
written holds only such data, so all of them still load.
"""

from __future__ import annotations

import copy
import errno
import pickle
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from flipviz.errors import UserError
from flipviz.files import atomic_path, free_bytes, need_space, signals_deferred

CHECKPOINT_NAME = "checkpoint.pt"
SPACE_RESERVE = 16e6  # bytes a checkpoint leaves free on its disk, for the recording written beside it


def checkpoint_path(path: Path | str) -> Path:
    """A checkpoint file, or a run folder holding checkpoint.pt -> the checkpoint file."""
    p = Path(path)
    if p.is_dir():
        p = p / CHECKPOINT_NAME
    if not p.is_file():
        raise FileNotFoundError(f"no checkpoint at {p}")
    return p


def save_checkpoint(path: Path, state: dict) -> Path:
    """Write `state` (plain data + tensors) to `path`, atomically; interrupts wait until it is written. A
    failed write (a full disk, a read-only folder) is a UserError naming the file; the last good
    checkpoint stays and no temporary file is left."""
    try:
        need_space(path, 1.05 * state_bytes(state) + SPACE_RESERVE, "the checkpoint")
        with signals_deferred(), atomic_path(path) as tmp:
            try:
                torch.save(state, tmp)
            except RuntimeError as e:  # torch's zip writer reports a failed write (a full disk) so, not as OSError
                free = free_bytes(tmp.parent)
                raise OSError(
                    errno.EIO,
                    f"the write failed, {free / 1e6:.0f} MB free on that disk ({str(e).splitlines()[0][:80]})",
                ) from None
    except OSError as e:
        kept = "the last good checkpoint is kept" if Path(path).is_file() else "no checkpoint was written yet"
        raise UserError(f"cannot write {path}: {e.strerror or e}; {kept}") from None
    return Path(path)


def tensors(state) -> Iterator[torch.Tensor]:
    """Every tensor in a (nested) state: dicts, lists and tuples are walked."""
    if isinstance(state, torch.Tensor):
        yield state
    elif isinstance(state, dict):
        for v in state.values():
            yield from tensors(v)
    elif isinstance(state, (list, tuple)):
        for v in state:
            yield from tensors(v)


def state_bytes(state) -> int:
    """The bytes of the tensors in a (nested) state: about a checkpoint's size on disk."""
    return sum(t.numel() * t.element_size() for t in tensors(state))


def load_checkpoint(path: Path | str, map_location: str | torch.device = "cpu") -> dict:
    """A checkpoint written by `save_checkpoint`; anything else (missing, truncated, foreign) is a UserError."""
    try:
        p = checkpoint_path(path)
    except FileNotFoundError as e:
        raise UserError(f"cannot open the run: {e}") from None
    try:
        state = torch.load(p, map_location=map_location, weights_only=True)  # never runs code from the file
    except pickle.UnpicklingError as e:
        if "GLOBAL" in str(e):  # the file names a Python object (a function, a class) to build
            raise UserError(
                f"cannot open {p}: it holds Python objects beyond tensors and plain data, and flipviz "
                "never loads those (loading could run code); it was not written by flipviz"
            ) from None
        raise UserError(f"cannot open {p}: not a readable checkpoint (UnpicklingError)") from None
    except Exception as e:  # truncated, garbage, another format: torch and pickle raise many kinds
        raise UserError(f"cannot open {p}: not a readable checkpoint ({type(e).__name__})") from None
    if not isinstance(state, dict) or "step" not in state or "model" not in state:
        raise UserError(f"cannot open {p}: not a flipviz checkpoint")
    return state


def state_is_finite(state_dict: dict) -> bool:
    """True when every floating tensor in a (possibly nested) state dict is finite."""
    return all(not t.is_floating_point() or bool(torch.isfinite(t).all()) for t in tensors(state_dict))


# What a crafted or foreign checkpoint raises while a run reads it back: each becomes one line.
MISFIT = (KeyError, ValueError, TypeError, RuntimeError, AttributeError, IndexError)


def is_count(value: object) -> bool:
    """A whole number >= 0 (a step, a step counter; not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def counter(state: dict, key: str, default: int | None = None) -> int:
    """The checkpoint's step counter `key` (step, field_start): a whole number >= 0, else ValueError."""
    value = state[key] if default is None else state.get(key, default)
    if not is_count(value):
        raise ValueError(f"{key} {value!r} is not a whole number >= 0")
    return value


def check_resumable(state: dict, mine: dict, path: Path | str, named_scene: bool) -> None:
    """A UserError unless the checkpoint's run is this one's: its method, field, scene (when the run names a
    built-in scene, not a folder) and configuration; `mine`: this run's settings."""
    theirs = state.get("config", {})
    if not isinstance(theirs, dict):
        raise UserError(f"cannot resume: {path} is not a flipviz checkpoint (its config is not a table)")
    for key in ("method", "field", "scene", "config"):
        if key in theirs and not isinstance(theirs[key], (str, int, type(None))):
            raise UserError(
                f"cannot resume: {path} is not a flipviz checkpoint (its {key} is a {type(theirs[key]).__name__})"
            )
        if key in theirs and theirs[key] != mine[key] and (key != "scene" or named_scene):
            raise UserError(f"cannot resume: {path} is a {key} {theirs[key]!r} run, this one is {mine[key]!r}")


def misfit_reason(e: BaseException) -> str:
    """One of MISFIT in a few words, for the one line a bad checkpoint gets."""
    return f"missing {e}" if isinstance(e, KeyError) else (str(e).splitlines() or [type(e).__name__])[0][:120]


@dataclass
class FieldSnapshot:
    """A field, its optimiser and the sampler's state at one of the field's steps, copied: what a rollback
    returns to (--after-drop rollback: the join)."""

    field_step: int
    model: dict
    opt: dict
    rng: torch.Tensor

    @classmethod
    def take(cls, model, opt: torch.optim.Optimizer, gen: torch.Generator, field_step: int) -> FieldSnapshot:
        return cls(field_step, copy.deepcopy(model.state_dict()), copy.deepcopy(opt.state_dict()), gen.get_state())

    def restore(self, model, gen: torch.Generator) -> torch.optim.Optimizer:
        """`model` and `gen` as they were; a new optimiser for the model, in its saved state."""
        model.load_state_dict(copy.deepcopy(self.model))
        opt = model.make_optimizer()
        opt.load_state_dict(copy.deepcopy(self.opt))
        gen.set_state(self.rng)
        return opt
