"""What a browser may set: every value a client sends is bounded on the server.

viser takes a GUI update from any client as it comes: a slider's value beyond its own min and max
(a "Max resolution" of 6000 px stalled training for minutes), NaN, a dropdown value that is none
of its options, even new min / max / options props. So the server keeps its own bounds, here, and
puts a value back inside them before any other callback of the element sees it (an async callback
registered first runs on viser's event loop, ahead of the others). The readers that matter also
clamp at the point of use (`bounded`), so no window between the update and the guard is exploitable.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

H = TypeVar("H")


def bounded(value: object, lo: float, hi: float, fallback: float) -> float:
    """`value` within [lo, hi]; a non-number, a bool or a non-finite number gives `fallback`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return fallback
    return min(max(value, lo), hi)


def guard_number(handle: H, lo: float, hi: float) -> H:
    """A slider or number input whose value the server keeps in [lo, hi] (its initial value for junk)."""
    initial = handle.value
    kind = type(initial)

    @handle.on_update
    async def _(_) -> None:
        v = handle.value
        fixed = kind(bounded(v, lo, hi, initial))
        if fixed != v or type(v) is not kind:
            handle.value = fixed

    return handle


def guard_choice(handle: H, options: Sequence[str]) -> H:
    """A dropdown whose value the server keeps among `options` (the fixed ones it was built with)."""
    allowed, initial = tuple(options), handle.value

    @handle.on_update
    async def _(_) -> None:
        if handle.value not in allowed:
            handle.value = initial

    return handle


def guard_vector(handle: H, limit: float) -> H:
    """A vector input whose components the server keeps finite and within +-limit."""
    initial = tuple(handle.value)

    @handle.on_update
    async def _(_) -> None:
        v = tuple(handle.value)
        fixed = tuple(bounded(x, -limit, limit, i) for x, i in zip(v, initial)) if len(v) == len(initial) else initial
        if fixed != v:
            handle.value = fixed

    return handle
