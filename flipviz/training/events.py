"""The observer interface: how visualisation (Rerun, viser) and tools watch training.

The trainer calls every registered observer from its own thread; observers copy what they need
and return quickly. All arrays are numpy (never torch), in the camera convention of
`flipviz.data.cameras`. Observers never reach into the trainer; to act on it (render a novel
view, pause) they use the trainer's public methods.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane
from flipviz.geometry.symmetry import PlaneEstimate
from flipviz.training.config import TrainConfig

# mirror_init: a mirrored camera at its initial pose; mirror: at its current (BA-refined) pose;
# mirror_true: the exact reflection through the scene's true symmetry plane.
CameraKind = Literal["input", "mirror_init", "mirror", "mirror_true", "test", "upper"]


def split_label(config: int) -> str:
    """How a run's views were chosen, in words: the protocol's configuration, or the user's inputs."""
    return f"configuration {config}" if config else "own inputs"


@dataclass
class CameraInfo:
    """A camera the run knows about, with its image (the flipped one for mirrors)."""

    kind: CameraKind
    camera: Camera
    image: np.ndarray | None = None  # (H, W, 3) float32
    source: str = ""  # for mirrors: the name of the input view it was flipped from
    alpha: np.ndarray | None = None  # (H, W) the true silhouette, where known (structure scores)


@dataclass
class SetupEvent:
    run_name: str
    scene: str
    method: str
    config: int  # protocol configuration 1..8; 0: protocol-free inputs (--inputs, captures)
    total_steps: int
    sphere_center: np.ndarray  # (3,) least-squares sphere through the input camera centres
    sphere_radius: float
    plane: Plane | None  # the mirror plane used (None when the method uses no mirrors)
    true_plane: Plane | None  # the scene's true symmetry plane, when known
    cameras: list[CameraInfo]
    bbox: np.ndarray  # (2, 3)
    cfg: TrainConfig = field(default_factory=TrainConfig)  # the run's settings, typed
    near: float = 2.0  # the scene's ray bounds (depth maps are coloured over them)
    far: float = 6.0
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # the scene's up (mirrors look-at)
    plane_estimate: PlaneEstimate | None = None  # --mirror-plane auto: the estimate and its scores


@dataclass
class StepEvent:
    step: int  # 1-based number of optimisation steps done
    total_steps: int
    elapsed_s: float
    scalars: dict[str, float]  # loss, psnr (training batch), lr_field, lr_pose, ...
    # Mirrored cameras (None when the method has none), in the order of SetupEvent's mirror_init.
    mirror_c2w: np.ndarray | None = None  # (M, 4, 4) current refined poses
    mirror_rot_change_deg: np.ndarray | None = None  # (M,) rotation change from the initial pose
    mirror_trans_change: np.ndarray | None = None  # (M,)
    mirror_rot_err_deg: np.ndarray | None = None  # (M,) vs the exact reflected pose, when known
    mirror_trans_err: np.ndarray | None = None  # (M,)
    mirror_ratio: np.ndarray | None = None  # (M,) each one's disagreement with the inputs (NaN: not measured yet)
    mirror_dropped_at: tuple[int | None, ...] | None = None  # (M,) the step each was dropped at (None: kept)
    plane: Plane | None = None  # the mirror plane now, when training refines it (--refine-plane)
    plane_err_deg: float | None = None  # its angle to the scene's true plane, when known
    plane_err_offset: float | None = None  # and its offset from it (scene units)


@dataclass
class RenderedView:
    name: str
    kind: CameraKind
    camera: Camera
    rgb: np.ndarray  # (H, W, 3)
    depth: np.ndarray  # (H, W)
    opacity: np.ndarray  # (H, W)
    beta2: np.ndarray | None = None  # (H, W) rendered variance beta_hat^2, when the model has it
    gt: np.ndarray | None = None  # (H, W, 3) ground truth (flipped image for mirrors)


@dataclass
class ImagesEvent:
    """Periodic renders: the unobserved test views and the mirrored views (with beta^2)."""

    step: int
    test_views: list[RenderedView]
    mirror_views: list[RenderedView]
    scalars: dict[str, float] = field(default_factory=dict)  # e.g. test_psnr


@dataclass
class EndEvent:
    step: int
    status: Literal["finished", "stopped", "nan", "error"]
    message: str = ""
    metrics: dict = field(default_factory=dict)


class Observer:
    """Base class: override what you need. Exceptions in observers are logged, never fatal."""

    def on_setup(self, event: SetupEvent) -> None: ...

    def on_step(self, event: StepEvent) -> None: ...

    def on_images(self, event: ImagesEvent) -> None: ...

    def on_end(self, event: EndEvent) -> None: ...
