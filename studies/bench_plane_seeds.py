"""How steady is the plane? (a script) The same inputs trained with several seeds: the spread of the
estimated plane (`auto`) and of the plane after training refines it (`--refine-plane`).

    python studies/bench_plane_seeds.py [--scenes chair,chair-turned,lego] [--configs 1] [--seeds 0,1,2,3,4]

Spread: the largest angle between two seeds' planes (degrees) and the largest difference of their
offsets along the first seed's normal; the error against the scene's true plane beside it. Writes
seeds.json and seeds.md into --out.
"""

from __future__ import annotations

import itertools
import os
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
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))


@dataclass
class Args:
    scenes: str = "chair,chair-turned"
    configs: str = "1"
    seeds: str = "0,1,2,3,4"
    threads: int = 2
    lego: Path = LEGO
    """The scene `lego` reads this NeRF-synthetic folder (it has no true plane here)."""
    out: Path = ROOT / "docs/results/plane_refine"


def spread(planes: list[Plane]) -> tuple[float, float]:
    """(largest angle between two planes, largest offset difference of two planes' points along the first normal)."""
    deg = max((plane_error(a, b)[0] for a, b in itertools.combinations(planes, 2)), default=0.0)
    n = planes[0].normal
    offsets = [float(p.point @ n) * float(np.sign(p.normal @ n)) for p in planes]
    return deg, max(offsets) - min(offsets)


def worst(planes: list[Plane], true: Plane | None) -> str:
    """The largest angle and the largest offset of the planes against the true plane ('-': none known)."""
    if true is None or not planes:
        return "-"
    errors = [plane_error(p, true) for p in planes]
    return f"{max(e[0] for e in errors):.2f}° / {max(e[1] for e in errors):.3f}"


def spread_cell(planes: list[Plane]) -> str:
    return "-" if not planes else "{:.2f}° / {:.3f}".format(*spread(planes))


def main(a: Args) -> None:
    torch.set_num_threads(a.threads)
    head = (
        "| scene | config | seeds | estimate: spread | worst error | refined: spread | worst error | "
        "mirrors dropped | PSNR min - max |"
    )
    rows, lines = [], [head, "|---|---|---|---|---|---|---|---|---|"]
    for scene in a.scenes.split(","):
        for config in (int(c) for c in a.configs.split(",")):
            est, ref, psnr = [], [], []
            for seed in (int(s) for s in a.seeds.split(",")):
                with tempfile.TemporaryDirectory() as tmp:
                    tr = Trainer(
                        TrainConfig.from_settings(
                            scene=scene,
                            data=a.lego if scene == "lego" else None,
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
                dropped = tr.flip.dropped_at is not None or not tr.spec.mirrors  # by the agreement gate
                refined = None if dropped else tr.flip.current_plane()  # a dropped plane froze where it was
                est.append(tr.mirrors.plane)
                ref += [refined] if refined is not None else []
                psnr.append(m["psnr"])
                true = tr.scene.symmetry_plane  # None: the object has no true mirror plane
                error = lambda p: plane_error(p, true) if p is not None and true is not None else None  # noqa: E731
                rows.append(
                    {
                        "scene": scene,
                        "config": config,
                        "seed": seed,
                        "psnr": m["psnr"],
                        "estimate": est[-1].to_dict(),
                        "refined": refined.to_dict() if refined is not None else None,
                        "estimate_error": error(est[-1]),
                        "refined_error": error(refined),
                        "dropped_at": tr.flip.dropped_at,
                    }
                )
                print(rows[-1])
            lines.append(
                f"| {scene} | {config} | {len(est)} | {spread_cell(est)} | {worst(est, true)} | {spread_cell(ref)} | "
                f"{worst(ref, true)} | {len(est) - len(ref)} | {min(psnr):.2f} - {max(psnr):.2f} |"
            )
    a.out.mkdir(parents=True, exist_ok=True)
    write_json(a.out / "seeds.json", rows)
    write_text(
        a.out / "seeds.md",
        "# The plane over seeds\n\n`python studies/bench_plane_seeds.py "
        f"--scenes {a.scenes} --configs {a.configs} --seeds {a.seeds}` (Flip+U at the defaults, the estimate kept "
        "even when doubted)\n\n" + "\n".join(lines) + "\n",
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
