"""Agreement per mirror or per region of a mirror? (a script; issue 41 asks to measure which)

Each Flip+U run trains with the gate off (every mirror kept) and records, besides each mirror's own ratio
(training/flip.py: Agreement.ratios), the same ratio for each tile of each mirrored image (`--tiles 2x2`:
quadrants; `2x1`: left and right halves): the running mean (the gate's AGREEMENT_EMA, over the batches
that drew at least MIN_MIRROR_RAYS of the tile's object rays) of the tile's object rays' squared error,
over the inputs'. Read from the training batches only (no extra render); the test PSNR is printed beside.

    python studies/bench_regions.py [--runs chair:7,lamp:1,...] [--tiles 2x2,2x1]

A diagnostic: it wraps `Flip.sample` and `Flip.loss` to see which pixels a batch drew (the gate itself
never needs them). Writes regions.json and regions.md into --out.
"""

from __future__ import annotations

import contextlib
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from flipviz.files import write_json, write_text
from flipviz.training import flip as F
from flipviz.training.config import TrainConfig
from flipviz.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
LEGO = ROOT.parent / "shared/data/nerf_synthetic/lego"


@dataclass
class Args:
    runs: str = "chair:1,chair:7,lamp:1,lamp:3,truck:1,mug:1,lego:5"
    """scene:configuration pairs (lego: the NeRF-synthetic scene at --lego)."""
    tiles: str = "2x2,2x1"
    """tiles across x down, one recording per entry."""
    steps: int = 600
    threads: int = 1
    lego: Path = LEGO
    out: Path = ROOT / "docs/results/agreement/regions"


class TileRecorder:
    """Each (mirror, tile)'s running ratio, step by step, from the batches `Flip` draws."""

    def __init__(self, across: int, down: int) -> None:
        self.across, self.down = across, down
        self.ema: torch.Tensor | None = None  # (M * T,) running squared error
        self.rows: list[tuple[int, list[float], list[float]]] = []  # (step, tile ratios, each mirror's): judged steps

    def tiles(self, flip: F.Flip, idx: torch.Tensor) -> torch.Tensor:
        """(R,) which tile of its image each drawn ray falls in (from its camera-frame direction)."""
        cam = flip.ts.views[0].camera
        d = flip.ts.bank.dirs_cam[idx]  # (R, 3), z = -1
        u = (d[:, 0] * cam.focal / cam.width + 0.5).clamp(0, 0.999)  # (R,) 0..1 across
        v = (-d[:, 1] * cam.focal / cam.height + 0.5).clamp(0, 0.999)  # (R,) 0..1 down
        return (u * self.across).long() + self.across * (v * self.down).long()

    def update(self, flip: F.Flip, idx: torch.Tensor, out: dict, target: torch.Tensor, view: torch.Tensor) -> None:
        a, n_tiles = flip.agreement, self.across * self.down
        sq = (out["rgb"] - target).pow(2).sum(-1)  # (R,)
        sel = F.object_rays(out, target) & a.is_mirror[view]  # (R,) the mirrored object rays, as Agreement's
        key = a.slot[view[sel]] * n_tiles + self.tiles(flip, idx)[sel]  # (K,) mirror * T + tile
        if self.ema is None:
            self.ema = torch.full((len(a.per_mirror) * n_tiles,), float("nan"), dtype=torch.float64)
        self.ema = F.running_means(self.ema, key, sq[sel])

    def record(self, flip: F.Flip, step: int) -> None:
        """The ratios after step `step`, once the gate would judge them (the NLL on)."""
        a = flip.agreement
        if self.ema is not None and a.input > 0 and step >= flip.gate_start:
            self.rows.append((step, (self.ema / a.input).tolist(), a.ratios.tolist()))


@contextlib.contextmanager
def recorded(rec: TileRecorder) -> Iterator[None]:
    """Flip's batches go through `rec` while inside (the methods are restored on leaving)."""
    sample, loss = F.Flip.sample, F.Flip.loss

    def drawn(self: F.Flip, n: int, generator: torch.Generator, step: int) -> torch.Tensor:
        self._drawn = sample(self, n, generator, step)
        return self._drawn

    def judged(self: F.Flip, out: dict, target: torch.Tensor, view: torch.Tensor, step: int) -> torch.Tensor:
        total = loss(self, out, target, view, step)
        if self.agreement is not None and self.dropped_at is None and step >= self.start:
            with torch.no_grad():
                rec.update(self, self._drawn, out, target, view)
            rec.record(self, step)
        return total

    F.Flip.sample, F.Flip.loss = drawn, judged
    try:
        yield
    finally:
        F.Flip.sample, F.Flip.loss = sample, loss


def run(a: Args, scene: str, config: int, across: int, down: int) -> dict:
    """One gate-off Flip+U run's ratios once the gate would judge them: peak and median, per mirror and tile."""
    source = {"data": a.lego} if scene == "lego" else {"scene": scene}
    rec = TileRecorder(across, down)
    with tempfile.TemporaryDirectory() as tmp, recorded(rec):
        cfg = TrainConfig.from_settings(
            config=config,
            steps=a.steps,
            out=Path(tmp) / "run",
            no_rrd=True,
            images_every=0,
            checkpoint_every=0,
            disagreement_limit=float("inf"),
            mirror_disagreement_limit=float("inf"),
            **source,
        )
        m = Trainer(cfg).run()
    rows = rec.rows
    tiles = np.array([r[1] for r in rows]).reshape(len(rows), -1, across * down)  # (S, M, T)
    each = np.array([r[2] for r in rows])  # (S, M)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a tile no batch drew enough of: NaN
        return {
            "scene": scene,
            "config": config,
            "tiles": f"{across}x{down}",
            "psnr": m["psnr"],
            "mirror_peak": np.nanmax(each, 0).tolist(),
            "mirror_median": np.nanmedian(each, 0).tolist(),
            "tile_peak": np.nanmax(tiles, 0).tolist(),
            "tile_median": np.nanmedian(tiles, 0).tolist(),
        }


def fmt(xs: list) -> str:
    return " ".join(f"{x:.2f}" for x in xs)


def main(a: Args) -> None:
    torch.set_num_threads(a.threads)
    results = []
    for tiles in a.tiles.split(","):
        across, down = (int(x) for x in tiles.split("x"))
        for item in a.runs.split(","):
            scene, config = item.split(":")
            r = run(a, scene, int(config), across, down)
            results.append(r)
            print(f"{item} {tiles}: test PSNR {r['psnr']:.2f}; each mirror's peak {fmt(r['mirror_peak'])}", flush=True)
            a.out.mkdir(parents=True, exist_ok=True)
            write_json(a.out / "regions.json", results)  # after each run: a stopped study keeps what it measured
    lines = ["# Agreement per mirror or per region of a mirror", ""]
    for tiles in dict.fromkeys(r["tiles"] for r in results):
        lines += [
            f"## Tiles {tiles} (across x down)",
            "",
            "Once the gate would judge (the NLL on), gate off. Each mirror: its own ratio's peak / median; "
            "then each tile's peak / median (tiles row by row).",
            "",
            "| scene | config | mirror | own peak / median | tiles' peaks | tiles' medians |",
            "|---|---|---|---|---|---|",
        ]
        for r in (r for r in results if r["tiles"] == tiles):
            for i, (peak, med) in enumerate(zip(r["mirror_peak"], r["mirror_median"])):
                lines.append(
                    f"| {r['scene']} | {r['config']} | {i} | {peak:.2f} / {med:.2f} | {fmt(r['tile_peak'][i])} "
                    f"| {fmt(r['tile_median'][i])} |"
                )
        lines.append("")
    write_text(a.out / "regions.md", "\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
