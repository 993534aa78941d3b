"""How steady is the plane? (a script) The same inputs trained with several seeds: the spread of the
estimated plane (`auto`) and of the plane after training refines it (`--refine-plane`).

    python benchmarks/bench_plane_seeds.py [--scenes chair,chair-turned] [--configs 1] [--seeds 0,1,2,3,4]

Spread: the largest angle between two seeds' planes (degrees) and the largest difference of their
offsets along the first seed's normal; the error against the scene's true plane beside it. Writes
seeds.json and seeds.md into --out.
"""

from __future__ import annotations

import itertools
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from flipviz.data.dataset import Plane
from flipviz.files import write_json, write_text
from flipviz.geometry.symmetry import plane_error
from flipviz.training.config import TrainConfig
from flipviz.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    scenes: str = "chair,chair-turned"
    configs: str = "1"
    seeds: str = "0,1,2,3,4"
    threads: int = 2
    out: Path = ROOT / "docs/results/plane_refine"


def spread(planes: list[Plane]) -> tuple[float, float]:
    """(largest angle between two planes, largest offset difference of two planes' points along the first normal)."""
    deg = max((plane_error(a, b)[0] for a, b in itertools.combinations(planes, 2)), default=0.0)
    n = planes[0].normal
    offsets = [float(p.point @ n) * float(np.sign(p.normal @ n)) for p in planes]
    return deg, max(offsets) - min(offsets)


def worst(planes: list[Plane], true: Plane) -> tuple[float, float]:
    """The largest angle and the largest offset of the planes against the true plane."""
    errors = [plane_error(p, true) for p in planes]
    return max(e[0] for e in errors), max(e[1] for e in errors)


def main(a: Args) -> None:
    torch.set_num_threads(a.threads)
    head = (
        "| scene | config | seeds | estimate: spread | worst error | refined: spread | worst error | PSNR min - max |"
    )
    rows, lines = [], [head, "|---|---|---|---|---|---|---|---|"]
    for scene in a.scenes.split(","):
        for config in (int(c) for c in a.configs.split(",")):
            est, ref, psnr = [], [], []
            for seed in (int(s) for s in a.seeds.split(",")):
                with tempfile.TemporaryDirectory() as tmp:
                    tr = Trainer(
                        TrainConfig(
                            scene=scene,
                            config=config,
                            seed=seed,
                            out=Path(tmp) / "run",
                            no_rrd=True,
                            images_every=0,
                            checkpoint_every=0,
                            unconfident_plane="use",
                        )
                    )
                    m = tr.run()
                est.append(tr.mirrors.plane)
                ref.append(tr.flip.current_plane())
                psnr.append(m["psnr"])
                true = tr.scene.symmetry_plane
                rows.append(
                    {
                        "scene": scene,
                        "config": config,
                        "seed": seed,
                        "psnr": m["psnr"],
                        "estimate": est[-1].to_dict(),
                        "refined": ref[-1].to_dict(),
                        "estimate_error": plane_error(est[-1], true),
                        "refined_error": plane_error(ref[-1], true),
                    }
                )
                print(rows[-1])
            (sd, so), (rd, ro), (ed, eo), (wd, wo) = spread(est), spread(ref), worst(est, true), worst(ref, true)
            lines.append(
                f"| {scene} | {config} | {len(est)} | {sd:.2f}° / {so:.3f} | {ed:.2f}° / {eo:.3f} | "
                f"{rd:.2f}° / {ro:.3f} | {wd:.2f}° / {wo:.3f} | {min(psnr):.2f} - {max(psnr):.2f} |"
            )
    a.out.mkdir(parents=True, exist_ok=True)
    write_json(a.out / "seeds.json", rows)
    write_text(
        a.out / "seeds.md",
        "# The plane over seeds\n\n`python benchmarks/bench_plane_seeds.py "
        f"--scenes {a.scenes} --configs {a.configs} --seeds {a.seeds}` (Flip+U at the defaults, the estimate kept "
        "even when doubted)\n\n" + "\n".join(lines) + "\n",
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
