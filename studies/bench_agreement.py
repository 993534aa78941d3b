"""Do the mirrors agree with the inputs? (a script) The training-batch disagreement of Flip+U runs
that keep their mirrors whatever the estimate's confidence (`--unconfident-plane use`), step by step.

    python studies/bench_agreement.py [--scenes chair,truck,mug,lamp] [--configs 1,4]

disagreement = the mirrored rays' squared error over the inputs' on the object (training/flip.py:
Agreement). Only training batches are read to draw the curves; the test PSNR is printed beside, to
report, never to choose. Writes agreement.json and agreement.md into --out.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from flipviz.files import write_json, write_text
from flipviz.training.config import FlipConfig, TrainConfig
from flipviz.training.events import Observer, StepEvent
from flipviz.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    scenes: str = "chair,truck,mug,lamp"
    configs: str = "1,4"
    steps: int = 600
    threads: int = 2
    gate: bool = False
    """Run with the agreement gate on (the default's behaviour); off: every run keeps its mirrors."""
    estimate_after: int = 150
    """--estimate-after of the runs (0: the plane from a separate fit, the mirrors from step 0)."""
    out: Path = ROOT / "docs/results/agreement"


class Curve(Observer):
    def __init__(self) -> None:
        self.rows: list[dict] = []

    def on_step(self, e: StepEvent) -> None:
        s = e.scalars
        row = {"step": e.step, **{k: s[k] for k in ("disagreement", "mse_mirror", "mse_input") if k in s}}
        if e.mirror_ratio is not None:  # each mirror's own (issue 41)
            row["per_mirror"] = [float(x) for x in e.mirror_ratio]
        self.rows.append(row)


def per_mirror_peaks(run: dict, gate_start: int) -> list[float]:
    """Each mirror's highest own ratio from the step the gate would judge it on (NaN where never measured)."""
    rows = [r["per_mirror"] for r in run["curve"] if r["step"] > gate_start and "per_mirror" in r]
    return np.nanmax(np.array(rows, dtype=float), axis=0).tolist() if rows else []


def main(a: Args) -> None:
    torch.set_num_threads(a.threads)
    runs = []
    for scene in a.scenes.split(","):
        for config in (int(c) for c in a.configs.split(",")):
            with tempfile.TemporaryDirectory() as tmp:
                cfg = TrainConfig.from_settings(
                    scene=scene,
                    config=config,
                    steps=a.steps,
                    out=Path(tmp) / "run",
                    no_rrd=True,
                    images_every=0,
                    checkpoint_every=0,
                    unconfident_plane="drop" if a.gate else "use",
                    disagreement_limit=FlipConfig.disagreement_limit if a.gate else float("inf"),
                    estimate_after=a.estimate_after,
                )
                tr = Trainer(cfg)
                curve = Curve()
                tr.add_observer(curve)
                m = tr.run()
            est = tr.plane_estimate
            run = {
                "scene": scene,
                "config": config,
                "confidence": est.confidence if est else None,
                "psnr": m["psnr"],
                "curve": curve.rows,
                "plane": m.get("plane", {}),
            }
            runs.append(run)
            d = [r.get("disagreement", np.nan) for r in curve.rows]
            print(
                f"{scene} c{config}: confidence {run['confidence']:.3f}, disagreement at 20/50/100% of the steps "
                f"{d[len(d) // 5]:.2f} / {d[len(d) // 2]:.2f} / {d[-1]:.2f}, test PSNR {m['psnr']:.2f}",
                flush=True,
            )
    a.out.mkdir(parents=True, exist_ok=True)
    write_json(a.out / "agreement.json", runs)
    lines = [
        "| scene | config | confidence | disagreement at 20% | 50% | 100% | each mirror's peak once the NLL is on "
        "| test PSNR |",
        "|---|---|---|---|---|---|---|---|",
    ]
    gate_start = a.estimate_after + int(FlipConfig.uncertainty_start * (a.steps - a.estimate_after))
    for r in runs:
        d = [c.get("disagreement", np.nan) for c in r["curve"]]
        peaks = " ".join(f"{x:.2f}" for x in per_mirror_peaks(r, gate_start))
        lines.append(
            f"| {r['scene']} | {r['config']} | {r['confidence']:.3f} | {d[len(d) // 5]:.2f} | {d[len(d) // 2]:.2f} | "
            f"{d[-1]:.2f} | {peaks} | {r['psnr']:.2f} |"
        )
    write_text(a.out / "agreement.md", "# Do the mirrors agree with the inputs?\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main(tyro.cli(Args))
