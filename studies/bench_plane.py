"""Plane benchmark (a script, not a test): does `--mirror-plane auto` find the plane, fast, and is it
as good as knowing it?

1. Estimate: plane error (degrees between normals, offset of the estimate's point from the true
   plane) and time of `auto` on every built-in scene, turned and not, and on lego (against x = 0,
   its approximate plane), for the protocol's configurations; the confidence on asymmetric scenes.
2. Training: Flip+U unobserved-view PSNR on the turned chair with the plane from `auto`, `official`
   (x = 0, wrong by the turn) and `scene` (the true plane), BA on and off, with B/L beside; and
   the paper's `lookat` initial pose against `reflect` (the default).
   Targets: `auto` within 0.3 dB of `scene`; `auto` in <= 15 s.

    python studies/bench_plane.py [--configs 1,2,3] [--skip-training | --skip-estimates] [--out docs/results/plane]

Writes estimates.json / training.json and a markdown summary (README.md) into --out. Timings on a
shared CPU are noisy: run it on an idle machine.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from flipviz.data import Plane, load_scene, make_split
from flipviz.data.scenes import SCENES
from flipviz.geometry.symmetry import CONFIDENT, plane_error
from flipviz.training.config import TrainConfig
from flipviz.training.plane_estimate import estimate_plane
from flipviz.training.run import train

LEGO = Path(os.environ.get("FLIPVIZ_LEGO", Path(__file__).resolve().parents[2] / "shared/data/nerf_synthetic/lego"))
LEGO_PLANE = Plane(np.zeros(3), np.array([1.0, 0.0, 0.0]))  # lego's approximate left-right plane


@dataclass
class Args:
    configs: str = "1,2,3,4,5,6,7,8"
    """Protocol configurations of the estimate part (comma-separated)."""
    scenes: str = ",".join(SCENES) + ",lego"
    """Scenes for the estimate part (lego when its folder exists)."""
    skip_training: bool = False
    """Only the estimate part."""
    skip_estimates: bool = False
    """Only the training part (the summary reuses --out's estimates.json when there is one)."""
    report_only: bool = False
    """Run nothing: rewrite README.md from --out's estimates.json and training.json."""
    train_configs: str = "1,4,7"
    """Configurations of the training part (turned chair)."""
    steps: int = 600
    out: Path = Path("docs/results/plane")


def estimates(args: Args) -> list[dict]:
    rows = []
    for name in args.scenes.split(","):
        if name == "lego" and not (LEGO / "transforms_test.json").is_file():
            print("lego not found: skipped")
            continue
        scene = load_scene(name, LEGO if name == "lego" else None, 100)
        truth = LEGO_PLANE if name == "lego" else scene.symmetry_plane
        for c in (int(x) for x in args.configs.split(",")):
            est = estimate_plane(make_split(scene, c).inputs, scene)
            row = {
                "scene": name,
                "config": c,
                "confidence": est.confidence,
                "confident": est.confident,
                "seconds": est.seconds,
                "fit_seconds": est.meta["fit_seconds"],
                "symmetric": truth is not None,
            }
            if truth is not None:
                row["error_deg"], row["error_offset"] = plane_error(est.plane, truth)
            rows.append(row)
            err = f"{row['error_deg']:5.2f} deg {row['error_offset']:.3f}" if truth is not None else "(asymmetric)"
            print(f"{name:14s} c{c} {err} confidence {est.confidence:.2f} {est.seconds:5.1f} s", flush=True)
    return rows


def training(args: Args) -> list[dict]:
    rows = []
    runs = [("bl", "official", True, "reflect")] + [
        ("flip+u", p, ba, "reflect") for p in ("auto", "scene", "official") for ba in (True, False)
    ]
    runs += [("flip+u", p, True, "lookat") for p in ("auto", "scene")]  # the paper's initial pose
    with tempfile.TemporaryDirectory() as tmp:
        for c in (int(x) for x in args.train_configs.split(",")):
            for method, plane, ba, pose in runs:
                cfg = TrainConfig.from_settings(
                    scene="chair-turned",
                    method=method,
                    config=c,
                    mirror_plane=plane,
                    ba=ba,
                    mirror_pose=pose,
                    steps=args.steps,
                    out=Path(tmp) / f"{method}-{plane}-{ba}-{pose}-{c}",
                    no_rrd=True,
                    images_every=0,
                )
                t0 = time.perf_counter()
                trainer, m = train(cfg)
                row = {
                    "config": c,
                    "method": method,
                    "plane": plane,
                    "ba": ba,
                    "pose": pose,
                    "psnr": m["psnr"],
                    "ssim": m["ssim"],
                    "seconds": time.perf_counter() - t0,
                    **{k: v for k, v in m.get("plane", {}).items() if k != "used"},
                }
                if "mirror_poses" in m and "mirror_rot_err_deg" in m["mirror_poses"]:
                    row["final_pose_err_deg"] = float(np.mean(m["mirror_poses"]["mirror_rot_err_deg"]))
                rows.append(row)
                print(
                    f"c{c} {method:6s} {plane:8s} {pose:7s} BA {'on ' if ba else 'off'} "
                    f"{m['psnr']:.2f} dB  {row['seconds']:.0f} s",
                    flush=True,
                )
    return rows


def summary(est: list[dict], tr: list[dict]) -> str:
    out = ["# --mirror-plane auto (studies/bench_plane.py)", ""]
    if est:
        out += [
            "## The estimate, per scene (mean over configurations; lego against x = 0)",
            "",
            "| scene | plane error (deg) | offset | confident | confidence | seconds |",
            "|---|---|---|---|---|---|",
        ]
        for name in dict.fromkeys(r["scene"] for r in est):
            rs = [r for r in est if r["scene"] == name]
            deg = (
                f"{np.mean([r['error_deg'] for r in rs]):.2f} (max {max(r['error_deg'] for r in rs):.2f})"
                if rs[0]["symmetric"]
                else "-"
            )
            off = f"{np.mean([r['error_offset'] for r in rs]):.3f}" if rs[0]["symmetric"] else "-"
            out.append(
                f"| {name} | {deg} | {off} | {sum(r['confident'] for r in rs)}/{len(rs)} | "
                f"{np.mean([r['confidence'] for r in rs]):.2f} | {np.mean([r['seconds'] for r in rs]):.1f} |"
            )
        out += [
            "",
            f"Confidence threshold {CONFIDENT} "
            "(tuned on the untouched chair, truck, mug and lamp, configurations 1 and 4).",
            "",
        ]
    if tr:
        out += [
            "## Flip+U on the turned chair: which plane, BA on / off (unobserved-view PSNR, dB)",
            "",
            "| run | " + " | ".join(f"config {c}" for c in dict.fromkeys(r["config"] for r in tr)) + " | mean |",
            "|---|" + "---|" * (len({r["config"] for r in tr}) + 1),
        ]
        for key in dict.fromkeys((r["method"], r["plane"], r["ba"], r["pose"]) for r in tr):
            rs = [r for r in tr if (r["method"], r["plane"], r["ba"], r["pose"]) == key]
            label = "B/L" if key[0] == "bl" else f"Flip+U, {key[1]}, {key[3]} pose, BA {'on' if key[2] else 'off'}"
            out.append(
                f"| {label} | "
                + " | ".join(f"{r['psnr']:.2f}" for r in rs)
                + f" | **{np.mean([r['psnr'] for r in rs]):.2f}** |"
            )
        out += [
            "",
            "Mean error of the mirrored poses against the exact reflections through the true plane at the end of",
            "training (rotation, degrees; with BA off it is the initial error):",
            "",
        ]
        for key in dict.fromkeys(
            (r["method"], r["plane"], r["ba"], r["pose"]) for r in tr if "final_pose_err_deg" in r
        ):
            rs = [r for r in tr if (r["method"], r["plane"], r["ba"], r["pose"]) == key]
            out.append(
                f"- {key[1]}, {key[3]} pose, BA {'on' if key[2] else 'off'}: "
                f"{np.mean([r['final_pose_err_deg'] for r in rs]):.2f} deg"
            )
    return "\n".join(out) + "\n"


def main(args: Args) -> None:
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "estimates.json"
    if args.report_only:
        read = lambda name: json.loads((args.out / name).read_text()) if (args.out / name).is_file() else []  # noqa: E731
        (args.out / "README.md").write_text(summary(read("estimates.json"), read("training.json")))
        return
    if args.skip_estimates:
        est = json.loads(saved.read_text()) if saved.is_file() else []
    else:
        est = estimates(args)
        saved.write_text(json.dumps(est, indent=1))
    tr = [] if args.skip_training else training(args)
    if tr:
        (args.out / "training.json").write_text(json.dumps(tr, indent=1))
    (args.out / "README.md").write_text(summary(est, tr))
    print(summary(est, tr))


if __name__ == "__main__":
    main(tyro.cli(Args))
