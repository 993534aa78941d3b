"""Training speed and PSNR of this tree against another commit's, side by side in one run (issue 43).

    git worktree add ../base c842c3d
    python studies/bench_step_speed.py --trees base=../base new=.           # speed, then quality
    python studies/bench_step_speed.py --trees a=../a b=../b --only speed

Speed: each case is the real command line (`flipviz train`, a fresh process, 2 threads as the CLI uses,
its recording and periodic renders on as by default), run --reps times per tree, the trees alternating
so that a slow spell of this shared machine hits both; the training time is metrics.json's
train_seconds (the steps only: not loading, the plane search, renders or evaluation). Quality: PSNR on the
unobserved views of the chair's and lego's configurations 1 and 5, flipviz's setting and the authors'
(`--preset authors --mirror-plane official`), once per tree (a run is deterministic for its seed).
Writes docs/results/step_speed/: results.json and README.md.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))
AUTHORS = ["--preset", "authors", "--mirror-plane", "official"]
SPEED = {  # case: the arguments of `flipviz train` after its defaults
    "chair, flipviz train's default (600 steps, 100 px)": ["--scene", "chair"],
    "chair, the app's default (3000 steps, 200 px)": ["--scene", "chair", "--steps", "3000", "--res", "200"],
    "lego, the authors' setting (600 steps, 100 px)": ["--data", str(LEGO), *AUTHORS],
}
QUALITY = [(scene, n, setting) for scene in ("chair", "lego") for n in (1, 5) for setting in ("fast", "authors")]


@dataclass
class Args:
    trees: tuple[str, ...] = ("base=../base", "new=.")
    """label=folder of each checkout to run (its flipviz package is imported from there)."""
    reps: int = 3
    """Timed runs per case and tree."""
    only: tuple[str, ...] = ("speed", "quality")
    cases: tuple[str, ...] = field(default_factory=lambda: tuple(SPEED))
    out: Path = ROOT / "docs/results/step_speed"


def train(tree: Path, args: list[str]) -> dict:
    """One `flipviz train` in a fresh process with `tree`'s flipviz; its metrics.json."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        env = dict(os.environ, PYTHONPATH=str(tree.resolve()))
        t0 = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "flipviz.cli", "train", *args, "--out", str(out)],
            cwd=tree, env=env, check=True, capture_output=True,
        )  # fmt: skip
        m = json.loads((out / "metrics.json").read_text())
        return {"train_seconds": m["train_seconds"], "psnr": m["psnr"], "wall_seconds": time.perf_counter() - t0}


def main(a: Args) -> None:
    trees = dict(t.split("=", 1) for t in a.trees)
    a.out.mkdir(parents=True, exist_ok=True)
    results: dict = {"trees": trees, "load": os.getloadavg(), "speed": {}, "quality": {}}
    if "speed" in a.only:
        for case in a.cases:
            runs = {label: [] for label in trees}
            for rep in range(a.reps):
                for label, tree in trees.items():
                    runs[label].append(train(Path(tree), SPEED[case]))
                    print(case, label, rep, runs[label][-1], flush=True)
            results["speed"][case] = runs
    if "quality" in a.only:
        for scene, n, setting in QUALITY:
            args = (["--data", str(LEGO)] if scene == "lego" else ["--scene", scene]) + ["--config", str(n)]
            args += AUTHORS if setting == "authors" else []
            key = f"{scene} {n} {setting}"
            results["quality"][key] = {label: train(Path(tree), args)["psnr"] for label, tree in trees.items()}
            print(key, results["quality"][key], flush=True)
    results["load_after"] = os.getloadavg()
    (a.out / "results.json").write_text(json.dumps(results, indent=1))
    (a.out / "README.md").write_text(report(results))


def report(r: dict) -> str:
    labels = list(r["trees"])
    lines = ["# Training speed and PSNR, side by side (studies/bench_step_speed.py)", ""]
    lines += [f"Trees: {', '.join(f'{k} = {v}' for k, v in r['trees'].items())}. Load average at the start "
              f"{r['load'][0]:.2f}, at the end {r['load_after'][0]:.2f}.", ""]  # fmt: skip
    if r["speed"]:
        head = " | ".join(f"{k}: training s (median; all)" for k in labels)
        lines += [f"| case | {head} | ratio {labels[0]} / {labels[-1]} | PSNR |", "|---" * (len(labels) + 3) + "|"]
        for case, runs in r["speed"].items():
            med = {k: statistics.median(x["train_seconds"] for x in runs[k]) for k in labels}
            every = {k: ", ".join(f"{x['train_seconds']:.1f}" for x in runs[k]) for k in labels}
            cells = [f"{med[k]:.1f} ({every[k]})" for k in labels]
            psnr = " / ".join(f"{runs[k][0]['psnr']:.2f}" for k in labels)
            lines.append(f"| {case} | {' | '.join(cells)} | {med[labels[0]] / med[labels[-1]]:.2f}x | {psnr} |")
        lines.append("")
    if r["quality"]:
        lines += [f"| PSNR (dB) | {' | '.join(labels)} | difference |", "|---" * (len(labels) + 2) + "|"]
        for key, by in r["quality"].items():
            diff = by[labels[-1]] - by[labels[0]]
            lines.append(f"| {key} | {' | '.join(f'{by[k]:.3f}' for k in labels)} | {diff:+.3f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main(tyro.cli(Args))
