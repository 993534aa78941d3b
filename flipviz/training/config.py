"""Run configuration: one dataclass, used by the CLI (tyro), the app and the benchmark."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

Method = Literal["bl", "bl+u", "flip", "flip+u", "upper"]
METHODS: tuple[str, ...] = ("bl", "bl+u", "flip", "flip+u", "upper")


@dataclass
class TrainConfig:
    """One training run of one method on one protocol configuration."""

    scene: str = "chair"
    """Built-in scene name (ignored when --data is given)."""
    data: Path | None = None
    """A Blender-format scene folder (transforms_test.json with the 200-view orbit)."""
    method: Method = "flip+u"
    """bl | bl+u | flip | flip+u | upper (the paper's five methods)."""
    config: int = 1
    """Protocol configuration n = 1..8 (which half ring is observed)."""
    res: int = 100
    """Image width in pixels (images are square)."""
    steps: int = 600
    """Optimisation steps."""
    batch_rays: int = 1024
    field: Literal["grid", "nerf"] = "grid"
    """grid: fast dense voxel grid (default); nerf: vanilla NeRF MLP, the paper's setting."""
    mirror_plane: str = "official"
    """opposite | official | scene | 'px,py,pz;nx,ny,nz' (a point and a normal)."""
    ba: bool = True
    """Bundle-adjust the mirrored poses (Flip methods)."""
    uncertainty: bool = True
    """Learned beta^2 on mirrored rays (Flip+U; --no-uncertainty gives the Table II ablation)."""
    refine: Literal["mirrored", "all"] = "mirrored"
    """Which poses BA refines."""
    seed: int = 0
    device: str = "cpu"
    """cpu | cuda | cuda:N."""
    out: Path | None = None
    """Run folder (default runs/<scene>-<method>-<config>-<time>)."""
    log_every: int = 10
    """Steps between StepEvents."""
    images_every: int = 250
    """Steps between ImagesEvents (test renders and beta^2 maps)."""
    rrd: Path | None = None
    """Rerun recording path (default <run folder>/recording.rrd)."""
    no_rrd: bool = False
    """Do not write a Rerun recording."""
    rerun_serve: bool = False
    """Also stream to a local Rerun web viewer (bound to 127.0.0.1) and print its URL."""
    resume: Path | None = None
    """Resume from a checkpoint file (or a run folder holding checkpoint.pt)."""
    uncertainty_start: float = 0.2
    """Fraction of the steps trained with plain MSE before the uncertainty loss starts (paper: 10k of 50k)."""
    density_weight: float = 0.01
    """w of the density regulariser (w / N_s) sum sigma in the uncertainty loss (paper Sec. IV-C)."""
    checkpoint_every: int = 500
    """Steps between checkpoints (atomic; a non-finite state is never written)."""
    eval_on_stop: bool = True
    """Evaluate the test views also when a run is stopped early."""
    beta2_mode: Literal["linear", "variance"] = "linear"
    """How the per-sample variances composite into beta_hat^2 (see flipviz/model/renderer.py)."""
    n_samples: int = 64
    """Samples per ray, in training and rendering. Measured on the chair at 100 px: 64 gives the
    same held-out PSNR as 128 (27.1 dB) at half the time."""
    grid_res: tuple[int, ...] | None = None
    """Grid field: voxels along the longest side, coarse to fine (None: the field's default)."""

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}
