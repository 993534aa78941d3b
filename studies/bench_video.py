"""Video benchmark (a script, not a test): how long `flipviz video` takes for a 100-frame, 200 px
video on this machine, for one run and for two (A/B), and the README's GIF of the unobserved side.

    python studies/bench_video.py [--runs RUN_BL RUN_FLIPU] [--out docs/results/video]
        [--gif assets/unobserved_bl_vs_flipu.gif]

Without --runs it first trains the chair, configuration 1, with B/L and Flip+U at the defaults of
`flipviz train` (600 steps, 100 px). Times are wall clock of `make_video` (opening the runs,
rendering every frame, ground truth, encoding), on an idle machine; writes results.json and README.md.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import imageio.v2 as imageio
import torch
import tyro

from flipviz.files import write_json, write_text
from flipviz.training.config import TrainConfig
from flipviz.training.run import train
from flipviz.viz.export.video import VideoConfig, make_video


@dataclass
class Args:
    runs: tuple[Path, Path] | None = None
    """A B/L and a Flip+U run folder of one scene (default: train the chair's, configuration 1)."""
    frames: int = 100
    res: int = 200
    out: Path = Path("docs/results/video")
    gif: Path | None = Path("assets/unobserved_bl_vs_flipu.gif")
    """The README's GIF: B/L vs Flip+U across the unobserved side (None: skip)."""


def timed(cfg: VideoConfig) -> dict:
    t0 = time.perf_counter()
    mp4, _ = make_video(cfg)
    seconds = time.perf_counter() - t0
    reader = imageio.get_reader(mp4)
    n, size = reader.count_frames(), reader.get_meta_data()["size"]
    reader.close()
    return {
        "path": cfg.path,
        "runs": len(cfg.runs),
        "frames": n,
        "size": list(size),
        "seconds": round(seconds, 1),
        "frames_per_s": round(n / seconds, 2),
        "mb": round(mp4.stat().st_size / 2**20, 2),
    }


def main(args: Args) -> None:
    tmp = Path(tempfile.mkdtemp(prefix="bench_video_"))
    if args.runs is None:
        runs = []
        for method in ("bl", "flip+u"):
            cfg = TrainConfig.from_settings(scene="chair", method=method, out=tmp / method)
            train(cfg)
            runs.append(cfg.output.out)
    else:
        runs = list(args.runs)
    rows = [
        timed(VideoConfig(runs=[runs[1]], path="orbit", frames=args.frames, res=args.res, out=tmp / "orbit.mp4")),
        timed(
            VideoConfig(runs=[runs[1]], path="unobserved", frames=args.frames, res=args.res, out=tmp / "unobserved.mp4")
        ),
        timed(
            VideoConfig(
                runs=runs, path="unobserved", frames=args.frames, res=args.res, out=tmp / "ab.mp4", gif=args.gif
            )
        ),
    ]
    machine = {
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "torch": torch.__version__,
    }
    write_json(args.out / "results.json", {"machine": machine, "runs": [str(r) for r in runs], "videos": rows})
    lines = [
        "# `flipviz video`: time for a 100-frame, 200 px video",
        "",
        f"Machine: {machine['cpus']} CPU cores, torch {machine['torch']} ({machine['torch_threads']} threads), no GPU. "
        "Runs: the chair, configuration 1, 600 steps at 100 px (the defaults of `flipviz train`), rendered at 200 px "
        "with 64 samples per ray. Wall time of `make_video`: opening the runs, rendering, ground truth (ray cast for "
        "built-in scenes), H.264 encoding. `python studies/bench_video.py` reproduces it.",
        "",
        "| path | runs | frames | frame size | seconds | frames/s | MB |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['path']} | {r['runs']} | {r['frames']} | {r['size'][0]} x {r['size'][1]} | {r['seconds']} | "
        f"{r['frames_per_s']} | {r['mb']} |"
        for r in rows
    ]
    lines += ["", "The unobserved path is rounded so that a frame lands on every test view (8 views: 7 gaps).", ""]
    write_text(args.out / "README.md", "\n".join(lines))
    print("\n".join(lines))
    print(json.dumps(rows))


if __name__ == "__main__":
    main(tyro.cli(Args))
