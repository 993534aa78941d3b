"""The current run as the app's panels see it: a small protocol that `viser_app.App` implements.

Panels (snap to view, novel cameras, the mirror lesson) read the run through it and render
through it; they never hold the app itself.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from flipviz.data.cameras import Camera
from flipviz.geometry.symmetry import PlaneEstimate
from flipviz.training.events import SetupEvent

OUTPUTS_ALL = ("rgb", "depth", "opacity", "beta2")


class RunView(Protocol):
    setup: SetupEvent | None  # the current run's setup (None before the first run starts)
    step: int  # optimisation steps done
    mirror_c2w: np.ndarray | None  # (M, 4, 4) the mirrored cameras' current (BA-refined) poses

    def render(self, camera: Camera, outputs: tuple[str, ...] = OUTPUTS_ALL) -> dict[str, np.ndarray] | None:
        """The current model seen from `camera` (None while no model exists); thread-safe."""
        ...

    def estimate_plane(self) -> PlaneEstimate | None:
        """The mirror plane estimated from the run's inputs (None while no run exists); slow (seconds)."""
        ...
