"""Which resolution should a run train at? PSNR and SSIM at 200 px against wall time (a script).

    python studies/bench_resolution.py [--scenes chair lego] [--methods bl upper] [--workers 2]

Each setting trains B/L and Upper on configuration 1 (600 steps of 1024 rays, 64 samples, the
defaults otherwise) and is scored at 200 px on **held-out views that the protocol never uses**:
- lego: the second turn of its test orbit (indices 100-195, every fifth; 20 to 47 degrees of
  elevation), never an input, test or Upper view;
- the built-ins: the 16 orbit views three indices past each ring view (3, 9, 15, ..., 97), never
  an input, test or Upper view (those are ring views and ring views + 1).
The unobserved test views are not looked at. Settings: the image width a run trains at, and the
grid's coarse-to-fine resolutions (voxels along the box's longest side). Each run's training
seconds are its steps alone (Trainer.train_seconds), and its run's are the whole of it (loading the
scene, the ray bank, the steps and scoring the protocol's test views); --workers runs go at once, one thread each.

It also renders one held-out view of each Upper run at 800 px and writes a crop of each side by
side (crops_<scene>.png): the crop box is fixed below, chosen before any render was looked at.
Writes docs/results/resolution/.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))
LEGO_HELD_OUT = tuple(range(100, 200, 5))  # the orbit's second turn: no protocol view is there
BUILTIN_HELD_OUT = tuple(i + 3 for i in (0, 6, 12, 19, 25, 31, 38, 44, 50, 56, 62, 69, 75, 81, 88, 94))
EVAL_RES = 200
CROP_RES, CROP = 800, (slice(250, 550), slice(250, 550))  # 300 x 300 px of the 800 px view's centre
SETTINGS: dict[str, tuple[int, tuple[int, ...]]] = {  # name: (training width, grid resolutions)
    "100 px, grid 64-128": (100, (64, 128)),
    "200 px, grid 64-128": (200, (64, 128)),
    "200 px, grid 96-192": (200, (96, 192)),
}


@dataclass
class Args:
    scenes: tuple[str, ...] = ("chair", "lego")
    methods: tuple[str, ...] = ("bl", "upper")
    settings: tuple[str, ...] = field(default_factory=lambda: tuple(SETTINGS))
    config: int = 1
    steps: int = 600
    workers: int = 2
    out: Path = ROOT / "docs/results/resolution"


def held_out(scene: str):
    """The held-out views of `scene` at EVAL_RES: (cameras, ground-truth images)."""
    if scene == "lego":
        from flipviz.data.blender import load_blender

        data = load_blender(LEGO, res=EVAL_RES)
        views = [data.views[i] for i in LEGO_HELD_OUT]
    else:
        from flipviz.data.builtin import load_builtin

        data = load_builtin(scene, res=EVAL_RES, indices=BUILTIN_HELD_OUT)
        views = [data.views[i] for i in BUILTIN_HELD_OUT]
    return [v.camera for v in views], [v.rgb for v in views]


def quiet_run(folder: Path, **settings):
    """A one-off run trained in `folder` on one thread (its own process's), with no recording, periodic
    renders or checkpoints: the held-out views are scored by the caller."""
    import torch

    from flipviz.training.config import TrainConfig
    from flipviz.training.setup import load_scene_for
    from flipviz.training.trainer import Trainer

    torch.set_num_threads(1)
    cfg = TrainConfig.from_settings(
        no_rrd=True, images_every=0, checkpoint_every=0, out=Path(folder) / "run", **settings
    )
    return Trainer(cfg, load_scene_for(cfg))


def crop_truth(scene: str, camera, truth: np.ndarray) -> np.ndarray:
    """The ground truth of the crop view at CROP_RES: a built-in's rendered there; lego's `truth` (its
    EVAL_RES image, all the data has) upsampled."""
    if scene == "lego":
        return np.repeat(np.repeat(truth, CROP_RES // EVAL_RES, 0), CROP_RES // EVAL_RES, 1)
    from flipviz.data.builtin import render_view

    return render_view(scene, camera.resized(CROP_RES))[0]


def train_one(job: tuple[str, str, str, int, int, str]) -> dict:
    """Train one (scene, method, setting) run in this process; its time and held-out scores."""
    import tempfile
    import time

    from flipviz.training.evaluate import image_psnr, ssim

    scene_name, method, setting, config, steps, out = job
    width, grid_res = SETTINGS[setting]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        trainer = quiet_run(
            tmp,
            scene=scene_name,
            data=LEGO if scene_name == "lego" else None,
            method=method,
            config=config,
            res=width,
            steps=steps,
            grid_res=grid_res,
        )
        trainer.run()  # its test-view scores are not read here
        run_seconds = time.perf_counter() - t0
        cams, truths = held_out(scene_name)
        preds = [trainer.render(c, ("rgb",))["rgb"] for c in cams]
        row = {
            "scene": scene_name,
            "method": method,
            "setting": setting,
            "train_width": width,
            "grid_res": list(grid_res),
            "train_seconds": trainer.train_seconds,
            "run_seconds": run_seconds,
            "held_out_psnr": float(np.mean([image_psnr(p, t) for p, t in zip(preds, truths)])),
            "held_out_ssim": float(np.mean([ssim(p, t) for p, t in zip(preds, truths)])),
        }
        if method == "upper":
            crop = trainer.render(cams[0].resized(CROP_RES), ("rgb",))["rgb"][CROP]
            np.save(Path(out) / f"crop_{scene_name}_{width}_{grid_res[-1]}.npy", crop)
    return row


def crops_figure(args: Args, scene: str) -> None:
    """One row: the ground truth's crop, then each setting's Upper crop, labelled."""
    import imageio.v3 as iio
    from PIL import Image, ImageDraw

    cams, truths = held_out(scene)
    truth = crop_truth(scene, cams[0], truths[0])[CROP]
    tiles = [("ground truth" + (" (200 px, upsampled)" if scene == "lego" else ""), truth)]
    for s in args.settings:
        width, grid_res = SETTINGS[s]
        path = args.out / f"crop_{scene}_{width}_{grid_res[-1]}.npy"
        tiles.append((f"Upper, {s}", np.load(path)))
        path.unlink()
    h, w = tiles[0][1].shape[:2]
    canvas = Image.new("RGB", (w * len(tiles), h + 22), "white")
    draw = ImageDraw.Draw(canvas)
    for k, (label, img) in enumerate(tiles):
        canvas.paste(Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)), (k * w, 22))
        draw.text((k * w + 6, 5), label, fill="black")
    iio.imwrite(args.out / f"crops_{scene}.png", np.asarray(canvas))


def table(rows: list[dict]) -> list[str]:
    lines = [
        "| scene | method | setting | training (s) | whole run (s) | held-out PSNR (dB) | held-out SSIM |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['method']} | {r['setting']} | {r['train_seconds']:.1f} | {r['run_seconds']:.1f} "
            f"| {r['held_out_psnr']:.2f} | {r['held_out_ssim']:.3f} |"
        )
    return lines


def main(args: Args) -> None:
    from flipviz.files import write_json, write_text

    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [
        (sc, m, s, args.config, args.steps, str(args.out))
        for sc in args.scenes
        for m in args.methods
        for s in args.settings
    ]
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(train_one, jobs))
    if "upper" in args.methods:
        for scene in args.scenes:
            crops_figure(args, scene)
    lines = [
        "# Training resolution: held-out quality at 200 px against time",
        "",
        f"`python studies/bench_resolution.py --steps {args.steps} --scenes {' '.join(args.scenes)}`: "
        f"configuration {args.config}, {args.steps} steps of 1024 rays, "
        f"64 samples, {args.workers} runs at a time with one thread each, on the 2-core machine. Held-out scores at "
        f"{EVAL_RES} px: lego, 20 views of its orbit's second turn; the built-ins, the 16 orbit views three indices "
        "past each ring view. Neither is ever an input, test or Upper view; the unobserved test views are not "
        "looked at.",
        "",
        *table(rows),
    ]
    write_json(args.out / "results.json", {"args": {**vars(args), "out": str(args.out)}, "rows": rows})
    write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(json.dumps(rows))


if __name__ == "__main__":
    main(tyro.cli(Args))
