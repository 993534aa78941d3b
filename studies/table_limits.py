"""Flip+U's gain over B/L per configuration, for bench folders that differ in one setting (a script)

Issue 41 compares the agreement gate's settings over all 8 configurations of each scene on the
protocol's test views: one bench folder per setting (`flipviz bench ... --out DIR`), B/L taken from
the folder that holds it. Nothing is trained here; it reads each folder's runs and writes one table.

    python studies/table_limits.py --scenes lamp,chair --variants "default=limit6_{scene},each over 4=limit4_{scene}"

`{scene}` in a folder name is replaced by the scene. Each cell: gain over B/L in dB, mirrors kept, and
Flip+U's wall time over B/L's where both ran in one bench (rough: the runs shared the machine with others).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from flipviz.bench.tables import read_table
from flipviz.files import write_text

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    scenes: str = "lamp,chair,chair-turned,mug,lego"
    variants: str = "default (each over 6)=limit6_{scene}|lego_defaults,pooled + each over 4=limit4_{scene}"
    """name=folder pairs, comma-separated; folders under --root, `{scene}` replaced by the scene; a|b: the
    first of them that holds a finished bench. A scene without one has no row for it."""
    baseline: str = "limit6_{scene}|lego_defaults"
    """The folder that holds each scene's B/L runs."""
    root: Path = ROOT / "docs/results/agreement"
    out: Path = ROOT / "docs/results/agreement/limits.md"


def runs(root: Path, folders: str, scene: str, method: str) -> tuple[str, dict[int, dict]] | None:
    """The first of `folders` ('a|b') that holds a finished bench of `scene` (its results.csv), with its
    runs of one method by configuration; None when none does."""
    for folder in folders.format(scene=scene).split("|"):
        rows = [r for r in read_table(root / folder) if r["scene"] == scene]
        if rows:
            return folder, {int(r["config"]): r for r in rows if r["status"] == "ok" and r["method"] == method}
    return None


def cell(flip: dict | None, bl: dict | None, one_bench: bool) -> tuple[str, float | None]:
    """One configuration's cell: gain, mirrors kept, and wall time over B/L's when both ran in one bench
    (`one_bench`; in separate benches the machine's load differed)."""
    if flip is None or bl is None:
        return "not run", None
    gain = float(flip["psnr"]) - float(bl["psnr"])
    cost = float(flip["wall_seconds"]) / float(bl["wall_seconds"])
    time = f", {cost:.2f}x" if one_bench else ""
    return f"{gain:+.2f}, {flip['kept_mirrors']}/{flip['n_mirrors']}{time}", gain


def main(args: Args) -> None:
    variants = dict(pair.split("=", 1) for pair in args.variants.split(","))
    lines = [
        "# Flip+U - B/L per configuration, by the gate's setting",
        "",
        "Protocol test views (8 unobserved), 100 px, 600 steps, the auto plane. Cell: gain in dB, mirrors kept,",
        "wall time over B/L's where both ran in one bench (rough: the machine was shared). Written by",
        "`python studies/table_limits.py`.",
        "",
        "| scene | setting | " + " | ".join(str(c) for c in range(1, 9)) + " | mean | worst |",
        "|---|---|" + "---|" * 10,
    ]
    for scene in args.scenes.split(","):
        bl_folder, bl = runs(args.root, args.baseline, scene, "bl") or (None, {})
        for name, folders in variants.items():
            found = runs(args.root, folders, scene, "flip+u")
            if found is None:
                continue
            folder, flip = found
            cells = [cell(flip.get(c), bl.get(c), folder == bl_folder) for c in range(1, 9)]
            gains = [g for _, g in cells if g is not None]
            summary = f"{np.mean(gains):+.2f} | {min(gains):+.2f}" if len(gains) == 8 else f"{len(gains)}/8 run | "
            lines.append(f"| {scene} | {name} | " + " | ".join(text for text, _ in cells) + f" | {summary} |")
    write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
