"""Why a configuration gains or loses (a script, not a test): the committed bench tables' gain
Flip+U - B/L per configuration beside how well that configuration's mirrored cameras cover its
unobserved views (flipviz/geometry/coverage.py), with the chart the bench draws.

    python studies/bench_coverage.py [--out docs/results/coverage]

No training: the coverage is geometry (the inputs, the plane and the pose rule those tables ran
with: `official` and `lookat`), the gains are read from the committed results.csv files. New bench
runs carry the same columns themselves (table.md, gain_vs_coverage.png).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from flipviz.bench.figures import gain_chart
from flipviz.bench.tables import gain, read_table
from flipviz.data import load_scene
from flipviz.data.protocol import make_split
from flipviz.files import write_text
from flipviz.geometry.coverage import coverage
from flipviz.geometry.mirror import make_mirror_set

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))
TABLES = {  # committed table -> the plane and pose it ran with (docs/results/README.md)
    "builtin_100px": ("official", "lookat"),
    "lego_100px_1200steps": ("official", "lookat"),
}


@dataclass
class Args:
    out: Path = ROOT / "docs/results/coverage"


def rows_with_coverage(table: str, plane: str, pose: str) -> list[dict]:
    """The table's main runs (no ablation rows), each with its configuration's coverage."""
    rows = []
    for r in read_table(ROOT / "docs/results" / table):
        if r["status"] != "ok" or (r["method"] == "flip+u" and r["ba"] != "True"):
            continue
        rows.append(
            {
                "scene": r["scene"],
                "method": r["method"],
                "config": int(r["config"]),
                "psnr": float(r["psnr"]),
                "status": "ok",
                "ba": r["ba"] == "True",
                "uncertainty": r["uncertainty"] == "True",
            }
        )
    cov: dict[tuple, dict] = {}
    for scene in sorted({r["scene"] for r in rows}):
        data = load_scene("lego", LEGO, 50) if scene == "lego" else load_scene(scene, None, 16)
        for n in range(1, 9):
            split = make_split(data, n)
            ms = make_mirror_set(split.inputs, plane, data.symmetry_plane, data.center, data.up, pose=pose)
            cov[(scene, n)] = coverage([v.camera for v in split.tests], [v.camera for v in ms.views], ms.sphere.center)
    for r in rows:
        r["metrics"] = {"coverage": cov[(r["scene"], r["config"])]}
    return rows


def main(args: Args) -> None:
    lines = [
        "# Why a configuration gains or loses: the mirrors' coverage of the unobserved views",
        "",
        "Gain: Flip+U - B/L PSNR (dB) of the committed tables. Coverage: per unobserved view, the angle (about the "
        "object's centre) to the nearest mirrored camera; its mean over the 8 views, and the share within 30 degrees. "
        "`python studies/bench_coverage.py` writes this page from the committed results.csv files (no training).",
        "",
    ]
    for table, (plane, pose) in TABLES.items():
        rows = rows_with_coverage(table, plane, pose)
        lines += [
            f"## {table} (plane `{plane}`, pose `{pose}`)",
            "",
            "| scene | config | gain (dB) | mean angle (deg) | within 30 deg |",
            "|---|---|---|---|---|",
        ]
        for scene in sorted({r["scene"] for r in rows}):
            gains, angles = [], []
            for n in range(1, 9):
                g = gain(rows, scene, n)
                c = next(r["metrics"]["coverage"] for r in rows if r["scene"] == scene and r["config"] == n)
                lines.append(f"| {scene} | {n} | {g:+.2f} | {c['mean_angle_deg']:.1f} | {c['within_30']:.0%} |")
                gains.append(g)
                angles.append(c["mean_angle_deg"])
            lines.append(f"| {scene} | correlation of gain and angle | {np.corrcoef(gains, angles)[0, 1]:+.2f} | | |")
        chart = gain_chart(rows, args.out / f"gain_vs_coverage_{table}.png")
        lines += ["", f"![gain against coverage, {table}]({chart.name})", ""]
    write_text(args.out / "README.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
