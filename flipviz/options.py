"""Every numeric option's bounds, stated once, beside the option: `steps: Annotated[int, Range(1, 10_000_000)]`.

`check_ranges(cfg)` refuses any value outside them (NaN, inf, a negative, zero or huge number) in one
`UserError` line. Every command (train, app, bench, video, report, compare, export-scene) calls it
first, before it locks, writes or loads anything; `tests/test_options.py` finds every numeric option
of every command's config and checks that it carries a `Range` and that each bound holds.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass

from flipviz.errors import UserError


@dataclass(frozen=True)
class Range:
    """The closed interval [lo, hi] a numeric option (each element of a tuple option) must lie in;
    hi may be inf where an infinite value means something (never NaN)."""

    lo: float
    hi: float

    def holds(self, value: object) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and self.lo <= value <= self.hi

    def words(self) -> str:
        return f"{self.lo}..{self.hi}"


def flag(name: str) -> str:
    """A field's command-line flag: `batch_rays` -> `--batch-rays`."""
    return "--" + name.replace("_", "-")


def base_type(hint: object) -> object:
    """The scalar type under Annotated, X | None and tuple[X, ...]: `tuple[int, ...] | None` -> int."""
    while True:
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin is typing.Annotated:
            hint = args[0]
        elif origin in (typing.Union, types.UnionType):
            rest = [a for a in args if a is not type(None)]
            if len(rest) != 1:
                return hint
            hint = rest[0]
        elif origin is tuple:
            hint = args[0]
        else:
            return hint


def is_numeric(hint: object) -> bool:
    return base_type(hint) in (int, float)


def range_of(hint: object) -> Range | None:
    return next((m for m in getattr(hint, "__metadata__", ()) if isinstance(m, Range)), None)


def option_name(field_name: str, hint: object) -> str:
    """The flag name tyro gives a field: its `tyro.conf.arg(name=...)`, else the field's name."""
    return next((m.name for m in getattr(hint, "__metadata__", ()) if getattr(m, "name", None)), field_name)


def options(cls: type) -> Iterator[tuple[str, tuple[str, ...], object]]:
    """Every option of a config class: (flag name, attribute path, annotated hint). Nested config groups
    (TrainConfig's data, engine, flip, output) are walked: their flags are flat (`--steps`)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        inner = typing.get_args(hints[f.name])[0] if typing.get_origin(hints[f.name]) is typing.Annotated else None
        if dataclasses.is_dataclass(inner):
            for name, path, hint in options(inner):
                yield name, (f.name, *path), hint
        else:
            yield option_name(f.name, hints[f.name]), (f.name,), hints[f.name]


def check_ranges(cfg: object) -> None:
    """Each numeric option of `cfg` within its Range, else one UserError line naming the flag and range."""
    for name, path, hint in options(type(cfg)):
        bounds = range_of(hint)
        if bounds is None:
            continue
        value: object = cfg
        for attr in path:
            value = getattr(value, attr)
        values = value if isinstance(value, (tuple, list)) else (value,)
        if any(v is not None and not bounds.holds(v) for v in values):
            raise UserError(f"{flag(name)} must be in {bounds.words()}, got {value!r}")
