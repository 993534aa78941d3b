"""The paper's evaluation protocol (Sec. IV-A), as the project fixed it, made exact.

Ring: the first turn of the source orbit, indices 0..99. The 16 ring views are
round(k * 100 / 16), k = 0..15, 22.5 degrees apart. Configuration n = 1..8 observes the ring
positions (2n - 2 + j) mod 16, j = 0..7 (a contiguous half ring); the other 8 ring views are the
unobserved test views. The Upper bound adds, for each test view at orbit index i, the view i + 1.
"""

from __future__ import annotations

from dataclasses import dataclass

from flipviz.data.cameras import View
from flipviz.data.dataset import DatasetError, SceneData
from flipviz.errors import UserError

N_RING = 16  # ring views
N_OBSERVED = 8  # input views per configuration
TURN = 100  # orbit indices per turn (3.6 degrees of azimuth each)
CONFIGS: tuple[int, ...] = tuple(range(1, 9))

# Python's round() is round-half-to-even: 12.5 -> 12, 37.5 -> 38, 62.5 -> 62, 87.5 -> 88,
# which is exactly the list written in PROTOCOL.md (checked below at import time).
RING_INDICES: tuple[int, ...] = tuple(round(k * TURN / N_RING) for k in range(N_RING))
assert RING_INDICES == (0, 6, 12, 19, 25, 31, 38, 44, 50, 56, 62, 69, 75, 81, 88, 94)


def _check_config(config: int) -> int:
    if isinstance(config, bool) or not isinstance(config, int) or config not in CONFIGS:
        raise UserError(f"protocol configuration must be an integer in 1..8, got {config!r}")
    return config


def observed_positions(n: int) -> list[int]:
    """Ring positions (0..15) observed by configuration n: (2n - 2 + j) mod 16, j = 0..7."""
    _check_config(n)
    return [(2 * n - 2 + j) % N_RING for j in range(N_OBSERVED)]


def unobserved_positions(n: int) -> list[int]:
    """Ring positions of the 8 unobserved test views of configuration n, in ring order."""
    _check_config(n)
    return [(2 * n - 2 + N_OBSERVED + j) % N_RING for j in range(N_RING - N_OBSERVED)]


def input_indices(n: int) -> list[int]:
    """Orbit indices of the 8 input views of configuration n."""
    return [RING_INDICES[p] for p in observed_positions(n)]


def unobserved_indices(n: int) -> list[int]:
    """Orbit indices of the 8 unobserved test views of configuration n."""
    return [RING_INDICES[p] for p in unobserved_positions(n)]


def upper_indices(n: int) -> list[int]:
    """Orbit indices of the Upper views: i + 1 for each test view i (never a test view itself)."""
    return [i + 1 for i in unobserved_indices(n)]


def protocol_indices() -> list[int]:
    """Every orbit index any configuration needs: the 16 ring views and their 16 Upper views."""
    return sorted(set(RING_INDICES) | {i + 1 for i in RING_INDICES})


@dataclass
class Split:
    """The views of one configuration: 8 inputs, 8 unobserved tests, 8 Upper views."""

    config: int
    inputs: list[View]
    tests: list[View]
    uppers: list[View]


def make_split(scene: SceneData, config: int) -> Split:
    """Pick the input, test and Upper views of configuration `config` (1..8) from `scene`."""
    _check_config(config)
    wanted = input_indices(config) + unobserved_indices(config) + upper_indices(config)
    missing = sorted(i for i in set(wanted) if i not in scene.views)
    if missing:
        raise DatasetError(
            f"scene {scene.name!r} lacks orbit views {missing} needed by protocol configuration {config}"
        )
    pick = lambda idx: [scene.views[i] for i in idx]  # noqa: E731
    return Split(config, pick(input_indices(config)), pick(unobserved_indices(config)), pick(upper_indices(config)))
