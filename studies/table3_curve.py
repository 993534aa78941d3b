"""Why does the chair score less at 10 000 steps than at 3000 in the authors' setting? (a script, issue 40)

One run of the Table III study's chair item (`--preset authors --mirror-plane official`, grid, 100 px), with
the unobserved views rendered every --every steps: their PSNR at their poses (flipviz's protocol, untuned)
and the training batches' PSNR over the steps. B/L moves no pose (BA is Flip's), so its curve is the
field's alone: a falling test curve under a rising training one is the field overfitting the 8 inputs.
Flip+U's untuned curve also carries BA's drift of the frame (`--refine all`; the authors' protocol tunes
each test pose to undo it; `--refine mirrored` keeps the inputs still).

    python studies/table3_curve.py --method bl
    python studies/table3_curve.py --method flip+u --refine mirrored
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro

from flipviz.bench.results import read_json
from flipviz.files import write_json
from flipviz.training.config import preset_config
from flipviz.training.events import ImagesEvent, Observer, StepEvent
from flipviz.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    method: str = "bl"
    refine: Literal["all", "mirrored"] = "all"
    """all: the authors' BA of every pose (the study's setting); mirrored: no input pose moves (Flip only)."""
    scene: str = "chair"
    data: Path | None = None
    """A scene folder instead of a built-in (lego: ../shared/data/nerf_synthetic/lego); named by its folder."""
    config: int = 1
    steps: int = 10_000
    every: int = 500
    threads: int = 1
    out: Path = ROOT / "docs/results/table3/curves"


class Curves(Observer):
    """The unobserved views' PSNR at each render, and the training batches' PSNR (a running mean over
    the steps between renders), written to `path` after each render: a stopped run keeps its curve."""

    def __init__(self, path: Path, settings: dict) -> None:
        self.path, self.settings = path, settings
        self.rows: list[dict] = []
        self.train: list[float] = []

    def on_step(self, e: StepEvent) -> None:
        self.train.append(e.scalars["psnr"])

    def on_images(self, e: ImagesEvent) -> None:
        train = sum(self.train) / len(self.train) if self.train else float("nan")
        self.rows.append({"step": e.step, "test_psnr": e.scalars.get("test_psnr"), "train_psnr": train})
        self.train = []
        print(f"step {e.step}: test {e.scalars.get('test_psnr', float('nan')):.2f}, batches {train:.2f}", flush=True)
        self.write()

    def write(self, psnr: float | None = None) -> None:
        """The curve so far; `psnr`: the run's final score, once it has ended."""
        write_json(self.path, {"settings": self.settings, "psnr": psnr, "curve": self.rows})


def main(a: Args) -> None:
    torch.set_num_threads(a.threads)
    ba = f"_refine_{a.refine}" if a.method in ("flip", "flip+u") else ""  # B/L, B/L+U and Upper move no pose
    name = f"{a.data.name if a.data else a.scene}_c{a.config}_{a.method}_{a.steps}{ba}"
    settings = vars(a) | {"out": str(a.out), "data": str(a.data) if a.data else None}
    curves = Curves(a.out / f"{name}.json", settings)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = preset_config(
            "authors",
            scene=a.scene,
            data=a.data,
            config=a.config,
            method=a.method,
            steps=a.steps,
            mirror_plane="official",
            refine=a.refine,
            images_every=a.every,
            out=Path(tmp) / "run",
            no_rrd=True,
            checkpoint_every=0,
        )
        trainer = Trainer(cfg)
        trainer.add_observer(curves)
        m = trainer.run()
    curves.write(m["psnr"])
    plot(a.out)


def plot(out: Path) -> None:
    """curves.png: every curve in `out`, the unobserved views' PSNR (solid) and the training batches' (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (test, train) = plt.subplots(1, 2, figsize=(10, 4))
    for path in sorted(out.glob("*.json")):
        run = read_json(path)
        label = path.stem + ("" if run["psnr"] is not None else " (unfinished)")
        steps = [r["step"] for r in run["curve"]]
        test.plot(steps, [r["test_psnr"] for r in run["curve"]], marker=".", label=label)
        train.plot(steps, [r["train_psnr"] for r in run["curve"]], linestyle="--", label=label)
    test.set(xlabel="step", ylabel="PSNR (dB)", title="the 8 unobserved views, at their poses")
    train.set(xlabel="step", ylabel="PSNR (dB)", title="training batches (the 8 inputs, and mirrors)")
    train.legend(fontsize=7, loc="lower right")  # the same runs in both panels; here it hides no curve
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main(tyro.cli(Args))
