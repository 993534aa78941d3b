"""`flipviz bench` settings (parsed by tyro in flipviz/cli.py) and the parsing of its lists."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from flipviz.errors import UserError
from flipviz.options import Range
from flipviz.training.config import (
    METHODS,
    BatchRays,
    DataConfig,
    EngineConfig,
    EvalConfig,
    EvalEvery,
    EvalSteps,
    FlipConfig,
    GridRes,
    Res,
    Samples,
    Seed,
    Steps,
    TrainConfig,
)


@dataclass
class BenchConfig:
    """Reproduce the paper's Table III (and Table II with --ablation): many runs, resumable."""

    scenes: str = "chair,mug"
    """Comma-separated scenes: built-in names, or Blender-format folders <data-root>/<scene>."""
    data_root: Path | None = None
    """Folder holding Blender-format scenes (e.g. .../nerf_synthetic) for non-built-in names."""
    methods: str = "all"
    """Comma-separated methods (bl, bl+u, flip, flip+u, upper) or 'all'."""
    configs: str = "1-8"
    """Protocol configurations: '1-8', '1,3,5' or '2'."""
    res: Res = DataConfig.res
    """Image width in pixels."""
    steps: Steps = EngineConfig.steps
    """Optimisation steps per run."""
    batch_rays: BatchRays = EngineConfig.batch_rays
    """Rays per optimisation step."""
    field: Literal["grid", "nerf"] = EngineConfig.field
    """Radiance field of every run (grid: fast dense voxel grid; nerf: the paper's MLP)."""
    n_samples: Samples = EngineConfig.n_samples
    """Samples per ray, in training and rendering."""
    grid_res: GridRes = EngineConfig.grid_res
    """Grid field: voxels along the longest side, coarse to fine (None: the field's default)."""
    out: Path = Path("bench")
    """Output folder: results.csv/json, table.md, figures, runs/<key>/ (one folder per run)."""
    workers: Annotated[int, Range(1, 256)] = 1
    """Runs at once on this machine (local executor, 1..256); each gets cores // workers threads."""
    executor: Literal["local", "ray"] = "local"
    """local: processes on this machine; ray: tasks on a Ray cluster (pip install flipviz[cluster])."""
    address: str | None = None
    """Ray cluster address (e.g. 'auto' or 'ray://host:10001'); default: start a local Ray."""
    cpus_per_run: Annotated[int, Range(0, 1024)] = 0
    """Threads (and Ray CPUs) per run, 0..1024; 0: cores // workers (local) or 1 (ray)."""
    ablation: bool = False
    """Also run Table II: Flip+U with bundle adjustment and uncertainty each on/off."""
    mirror_plane: str = FlipConfig.mirror_plane
    """Mirror plane of the Flip runs: auto (estimated from each run's inputs) | official (x = 0, the
    authors' code) | opposite | scene | 'px,py,pz;nx,ny,nz'."""
    mirror_pose: Literal["reflect", "lookat"] = FlipConfig.mirror_pose
    """Initial mirrored poses: reflect (each camera reflected through the plane) | lookat (the paper's)."""
    refine_plane: bool = FlipConfig.refine_plane
    """Flip runs refine the mirror plane during training (TrainConfig.refine_plane)."""
    unconfident_plane: Literal["drop", "use"] = FlipConfig.unconfident_plane
    """Flip runs with an unconfident auto plane: use its mirrors (the agreement gate may drop them) or drop
    them at setup (the run then takes its B/L twin's result)."""
    mirror_disagreement_limit: Annotated[float, Range(1.0, float("inf"))] = FlipConfig.mirror_disagreement_limit
    """A single mirrored view is dropped when its own disagreement passes this (TrainConfig's); inf: never."""
    after_drop: Literal["rollback", "restart", "continue"] = FlipConfig.after_drop
    """When the agreement gate drops mirrors: roll the field back to the join, restart it once all are
    dropped, or continue it (TrainConfig.after_drop)."""
    eval_views: Literal["unobserved", "orbit"] = EvalConfig.eval_views
    """Every run's test views: the protocol's 8 unobserved (flipviz) or every orbit view it did not train on."""
    eval_tune_steps: EvalSteps = EvalConfig.eval_tune_steps
    """Every run's test poses tuned on their ground truth for this many Adam steps first (the authors': 100)."""
    eval_every: EvalEvery = EvalConfig.eval_every
    """Score every n-th of those views (1: all)."""
    preset: Literal["fast", "authors", "paper"] = TrainConfig.preset
    """Every run's preset: fast (flipviz's setting) | authors (the official code's loss and rendering
    choices on the grid; with --mirror-plane official, its x = 0) | paper (those on the paper's NeRF). An
    option you pass wins over the preset's; in code, build with training.config.preset_config(name, BenchConfig)."""
    seed: Seed = EngineConfig.seed
    """Seed of every run (each run is independent and seeded)."""
    device: str = EngineConfig.device
    """Device of every run: cpu | cuda | cuda:N."""
    retry_failed: bool = True
    """On restart, run failed runs again (finished runs are always skipped)."""
    keep_checkpoints: bool = False
    """Keep each finished run's checkpoint.pt (large); by default only results and renders stay."""
    grid_views: Annotated[int, Range(1, 8)] = 4
    """Unobserved views shown in the qualitative grid (1..8: the protocol has 8)."""
    report_only: bool = False
    """Train nothing: rebuild the reports from every result in <out>/runs/ (e.g. after a code change)."""
    quiet: bool = False
    """No progress bars (the log lines stay)."""


def parse_list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def parse_methods(text: str) -> list[str]:
    names = parse_list(text.lower())
    if names == ["all"]:
        return list(METHODS)
    bad = [m for m in names if m not in METHODS]
    if bad or not names:
        raise UserError(f"unknown method(s) {bad or text!r}: choose from {', '.join(METHODS)} or 'all'")
    return list(dict.fromkeys(names))


def parse_configs(text: str) -> list[int]:
    """'1-8' -> [1..8]; '1,3,5' -> [1, 3, 5]; ranges and lists may mix ('1-3,7')."""
    out: list[int] = []
    try:
        for part in parse_list(text):
            lo, _, hi = part.partition("-")
            out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        raise UserError(f"--configs must look like '1-8' or '1,3,5', got {text!r}") from None
    if not out or any(n < 1 or n > 8 for n in out):
        raise UserError(f"--configs must be protocol configurations in 1..8, got {text!r}")
    return list(dict.fromkeys(out))
