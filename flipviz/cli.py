"""The `flipviz` command line: one tyro CLI with a subcommand per tool.

    flipviz train --scene chair --method flip+u --config 3
    flipviz app --scene mug                  (same as `python app.py --scene mug`)
    flipviz bench --scenes chair,lego --data-root ../shared/data/nerf_synthetic
    flipviz export-scene chair out/chair
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable

import tyro

from flipviz.data.dataset import DatasetError
from flipviz.training.config import TrainConfig


@dataclass
class ExportScene:
    """Write a built-in scene in the Blender format (transforms_test.json + PNGs)."""

    scene: Annotated[str, tyro.conf.Positional]
    """Built-in scene name."""
    out_dir: Annotated[Path, tyro.conf.Positional]
    """Folder to write."""
    res: int = 100
    """Image width in pixels."""


def _train(cfg: TrainConfig) -> int:
    from flipviz.training.run import train
    from flipviz.training.trainer import default_run_dir, scene_label

    if cfg.out is None:
        cfg.out = default_run_dir(cfg, scene_label(cfg))
    rerun = None
    if not cfg.no_rrd or cfg.rerun_serve:
        from flipviz.viz.rerun_observer import make_rerun_observer

        rerun = make_rerun_observer(cfg, cfg.out)
    try:
        metrics = train(cfg, extra_observers=[rerun] if rerun else [])
        if rerun is not None and cfg.rerun_serve:
            _serve_until_interrupted(rerun.viewer_url)
    finally:  # also on Ctrl-C during setup: finalise whatever the recording already holds
        if rerun is not None:
            rerun.close()
    return 0 if metrics.get("status", "finished") in ("finished", "stopped") else 1


def _serve_until_interrupted(url: str | None) -> None:
    print(f"training done; Rerun web viewer still at {url} (Ctrl-C to quit)", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass


def _export(cmd: ExportScene) -> int:
    from flipviz.data.blender import export_scene

    export_scene(cmd.scene, cmd.out_dir, res=cmd.res)
    print(f"wrote {cmd.scene} to {cmd.out_dir}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from flipviz.bench import BenchConfig
    from flipviz.viz.viser_app import AppConfig

    cmd = tyro.extras.subcommand_cli_from_dict(
        {"train": TrainConfig, "app": AppConfig, "bench": BenchConfig, "export-scene": ExportScene},
        args=argv,
        description=__doc__,
    )
    return guarded(lambda: _dispatch(cmd))


def _dispatch(cmd) -> int:
    from flipviz.bench import BenchConfig, run_bench
    from flipviz.viz.viser_app import AppConfig, run_app

    if isinstance(cmd, AppConfig):  # AppConfig extends TrainConfig: test it first
        run_app(cmd)
        return 0
    if isinstance(cmd, TrainConfig):
        return _train(cmd)
    if isinstance(cmd, BenchConfig):
        print(f"results: {run_bench(cmd)}")
        return 0
    return _export(cmd)


def guarded(fn: Callable[[], int]) -> int:
    """Run a command; bad input is one line on stderr (exit 2), Ctrl-C outside a training loop exit 130."""
    try:
        return fn()
    except (DatasetError, ValueError) as e:  # bad input: one line, no traceback
        print(f"flipviz: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C outside the training loop (setup, loading): no traceback
        print("flipviz: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
