"""Does refining the plane during training recover the unobserved side without an oracle? (a script)

Runs `flipviz bench` at the defaults (100 px, 600 steps, `--mirror-plane auto` with its confidence
gate) for B/L and Flip+U with the plane refined (the default), and Flip+U with it fixed
(`--no-refine-plane`, the previous default), on every configuration of each scene, then writes the
issue's table: the gain Flip+U - B/L per scene, configurations 1 and 5 of the chair, and the
plane's error against the scene's true plane before and after training (lego: against x = 0, its
approximate plane).

    python studies/bench_plane_refine.py [--scenes chair,chair-turned,mug,lamp] [--lego]
        [--out docs/results/plane_refine]

Each bench keeps its own folder under --out (resumable: run the same command again). Nothing here
picks a setting: the plane's learning rate and BA's start were chosen on held-out views
(training/config.py says which).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from flipviz.bench.config import BenchConfig
from flipviz.bench.runner import run_bench
from flipviz.bench.tables import read_table
from flipviz.files import write_text

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))


@dataclass
class Args:
    scenes: str = "chair,chair-turned,mug,lamp"
    lego: bool = False
    """Also lego (its B/L and Flip+U runs: about 25 minutes on 2 cores)."""
    configs: str = "1-8"
    workers: int = 2
    out: Path = ROOT / "docs/results/plane_refine"


def rows(folder: Path) -> list[dict]:
    return [r for r in read_table(folder) if r["status"] == "ok"]


def num(r: dict, key: str) -> float | None:
    return float(r[key]) if r.get(key) not in (None, "", "None") else None


def summary(on: list[dict], off: list[dict], scenes: list[str]) -> str:
    """The issue's table from the two benches' rows."""
    head = (
        "| scene | B/L | Flip+U, plane fixed | Flip+U, plane refined | gain fixed | gain refined | "
        "configs 1 / 5 gain refined | plane error before (max over configs) | after (max) | mirrors dropped |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for scene in scenes:
        pick = lambda rs, m: {int(r["config"]): r for r in rs if r["scene"] == scene and r["method"] == m}  # noqa: E731
        bl, fixed, refined = pick(on, "bl"), pick(off, "flip+u"), pick(on, "flip+u")
        if not bl or not refined:
            continue
        mean = lambda d: float(np.mean([num(r, "psnr") for r in d.values()]))  # noqa: E731
        g = {n: num(refined[n], "psnr") - num(bl[n], "psnr") for n in refined if n in bl}
        kept = [r for r in refined.values() if r.get("mirrors_trained") == "True"]
        before, off_b = [num(r, "plane_error_deg") for r in kept], [num(r, "plane_error_offset") for r in kept]
        after, off_a = [num(r, "refined_error_deg") for r in kept], [num(r, "refined_error_offset") for r in kept]
        dropped = sum(r.get("mirrors_trained") == "False" for r in refined.values())
        err = lambda d, o: f"{max(d):.2f}° / {max(o):.3f}" if d and None not in d else "-"  # noqa: E731
        cells = [
            scene,
            f"{mean(bl):.2f}",
            f"{mean(fixed):.2f}" if fixed else "-",
            f"{mean(refined):.2f}",
            f"{mean(fixed) - mean(bl):+.2f}" if fixed else "-",
            f"{mean(refined) - mean(bl):+.2f}",
            " / ".join(f"{g[n]:+.2f}" if n in g else "-" for n in (1, 5)),
            err(before, off_b),
            err(after, off_a),
            f"{dropped} of {len(refined)}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(a: Args) -> None:
    scenes = [s for s in a.scenes.split(",") if s] + (["lego"] if a.lego else [])
    data_root = LEGO.parent if a.lego else None
    common = dict(scenes=",".join(scenes), configs=a.configs, workers=a.workers, data_root=data_root)
    on = run_bench(BenchConfig(**common, methods="bl,flip+u", out=a.out / "refined"))
    off = run_bench(BenchConfig(**common, methods="flip+u", refine_plane=False, out=a.out / "fixed"))
    table = summary(rows(on), rows(off), scenes)
    write_text(
        a.out / "README.md",
        "# The plane refined during training\n\n`python studies/bench_plane_refine.py"
        f"{' --lego' if a.lego else ''}`: B/L and Flip+U at the defaults, 100 px, 600 steps, configurations "
        f"{a.configs}; Flip+U with the plane refined (`refined/`) and fixed (`fixed/`).\n\n{table}\n",
    )
    print(table)


if __name__ == "__main__":
    main(tyro.cli(Args))
