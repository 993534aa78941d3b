"""What a run's Rerun recording costs to open: chunks, size and read time (issue 26, item 7).

    python studies/bench_recording.py [--scene chair] [--steps 600]

Trains one run (Flip+U at the defaults, 100 px) recording to an .rrd with the compaction at the end
switched off, keeps a copy, compacts it with `optimize_recording` (Rerun's `rerun rrd optimize`, as
every run does when it ends), and reports for both files: size, chunks (`rerun.chunk.RrdReader`),
the median time to read them all, and `rerun rrd verify`'s time (a process start included).
The scalar curves are batched while logging (`RerunObserver._scalar`: one `send_columns` per entity
and flush); run it at an older commit for the per-step `log` it replaced.
"""

from __future__ import annotations

import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


@dataclass
class Args:
    scene: str = "chair"
    method: str = "flip+u"
    steps: int = 600
    res: int = 100
    reads: int = 5
    """Reads timed per file (the median is reported)."""
    out: Path | None = None
    """Write the figures here as JSON."""


def read_all(path: Path) -> int:
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sum(1 for _ in RrdReader(str(path)).stream())


def measure(path: Path, reads: int) -> dict:
    from flipviz.viz.rerun.viewer import _rerun_cli

    times = []
    for _ in range(reads):
        t = time.perf_counter()
        chunks = read_all(path)
        times.append(time.perf_counter() - t)
    t = time.perf_counter()
    subprocess.run([*_rerun_cli(), "rrd", "verify", str(path)], check=True, capture_output=True)
    return {
        "bytes": path.stat().st_size,
        "chunks": chunks,
        "read_ms": 1e3 * statistics.median(times),
        "verify_ms": 1e3 * (time.perf_counter() - t),
    }


def main(args: Args) -> None:
    from flipviz.training.config import TrainConfig
    from flipviz.training.trainer import Trainer
    from flipviz.viz.rerun.observer import make_rerun_observer, optimize_recording

    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig.from_settings(
            scene=args.scene, method=args.method, steps=args.steps, res=args.res, out=Path(tmp) / "run"
        )
        trainer = Trainer(cfg)
        obs = make_rerun_observer(cfg, trainer.run_dir, optimize=False)
        trainer.add_observer(obs)
        trainer.run()
        obs.close()
        raw = obs.opts.path
        compact = Path(tmp) / "compacted.rrd"
        shutil.copy(raw, compact)
        t = time.perf_counter()
        optimize_recording(compact)
        compaction_s = time.perf_counter() - t
        result = {
            "as_logged": measure(raw, args.reads),
            "compacted": measure(compact, args.reads),
            "compaction_s": compaction_s,
            "scene": args.scene,
            "steps": args.steps,
            "res": args.res,
        }
    for k in ("as_logged", "compacted"):
        m = result[k]
        print(
            f"{k:10s}: {m['bytes'] / 1e6:.2f} MB, {m['chunks']} chunks, "
            f"read {m['read_ms']:.0f} ms, verify {m['verify_ms']:.0f} ms"
        )
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main(tyro.cli(Args))
