"""The current run as the app's panels see it: a small protocol that `viser_app.App` implements.

Panels (snap to view, novel cameras, the mirror lesson, the 3D preview, each browser's view) read
the run through it and render through it; they never hold the app itself.
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

    @property
    def training(self) -> bool:
        """Optimisation is under way (not building, paused, stopped or finished): the model changes."""
        ...

    def render(self, camera: Camera, outputs: tuple[str, ...] = OUTPUTS_ALL) -> dict[str, np.ndarray] | None:
        """The current model seen from `camera` (None while no model exists); thread-safe."""
        ...

    def point_cloud(self) -> dict[str, np.ndarray] | None:
        """The current field baked for the 3D preview (RadianceModel.point_cloud; None while no model)."""
        ...

    def estimate_plane(self) -> PlaneEstimate | None:
        """The mirror plane estimated from the run's inputs (None while no run exists); slow (seconds)."""
        ...


def depth_range(setup: SetupEvent | None) -> tuple[float, float]:
    """The depth colour scale of a run's views: its scene box seen from the fitted sphere's radius."""
    if setup is None:
        return (2.0, 6.0)
    half = 0.5 * float(np.linalg.norm(setup.bbox[1] - setup.bbox[0]))
    return (round(max(0.0, setup.sphere_radius - half), 2), round(setup.sphere_radius + half, 2))
