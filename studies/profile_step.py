"""Where a training step's milliseconds go, and how far each part is from this machine's floor.

    python studies/profile_step.py                                   # every case below, 2 threads
    python studies/profile_step.py --cases chair-fast-100

A case is one default-length run (600 steps, Flip+U, configuration 1, the plane fixed at x = 0 so that the
mirrors train from step 0) trained in this process, without a recording or periodic renders. Three windows
of it are timed, then profiled: the first steps (64^3, no occupancy mask yet: every sample is looked up),
64^3 with the mask, and 128^3 (the grid upsampled at a quarter of the steps). The functions a step passes
through are wrapped in `record_function` scopes for the profiled steps only (`SCOPES`); each op belongs
to the innermost scope around it, the backward and the optimiser to their own events. A step's wall time
is measured on the steps just before, without the profiler.

The floor of each part is the time its unavoidable work takes at this CPU's measured rates: sgemm
(the MLPs' FLOPs, forward and backward) and a STREAM-like copy (the bytes a part must move). The dense
grid's gradient and Adam move the whole grid each step; a sparse update needs only the voxels the
batch touched: both floors are given. Run it on an idle machine; it writes docs/results/profile_step/.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
LEGO = ROOT.parent / "shared/data/nerf_synthetic/lego"

CASES = {  # name: (scene, preset, res)
    "chair-fast-100": ("chair", "fast", 100),
    "chair-fast-200": ("chair", "fast", 200),
    "lego-authors-100": ("lego", "authors", 100),
    "lego-authors-200": ("lego", "authors", 200),
}
WINDOWS = {"64^3, no mask": (20, 80), "64^3": (110, 150), "128^3": (440, 500)}  # [first, last) steps
# The functions a step passes through, each timed as a scope of its own (`scopes`); an op belongs to the
# innermost scope around it. render_rays' own ops are sampling before the field's query, compositing after.
SCOPES = {
    "flipviz.training.flip:Flip.sample": "sampling",
    "flipviz.training.trainer:rays_from_c2w": "sampling",
    "flipviz.model.radiance:render_rays": "render_rays",
    "flipviz.model.grid_field:GridField.occupied": "occupancy",
    "flipviz.model.grid_field:GridField.query": "occupancy",
    "flipviz.model.grid_field:GridField.corners": "gathers",
    "flipviz.model.grid_field:GridField._lerp": "gathers",
    "flipviz.model.grid_field:GridField._density": "density & colour MLP",
    "flipviz.model.grid_field:GridField._color": "density & colour MLP",
    "flipviz.training.flip:Flip.loss": "objective",
    "flipviz.model.radiance:RadianceModel.regulariser": "regularisers (TV, entropy)",
    "flipviz.training.flip:Flip.poses": "Flip hooks",
    "flipviz.training.flip:Flip.after_step": "Flip hooks",
    "flipviz.training.flip:Agreement.update": "Flip hooks",
    "flipviz.model.radiance:RadianceModel.update_schedule": "schedule (occupancy refresh)",
}


@dataclass
class Args:
    cases: tuple[str, ...] = tuple(CASES)
    """Which cases to profile (CASES)."""
    threads: int = 2
    out: Path = ROOT / "docs/results/profile_step"


@contextmanager
def scopes() -> Iterator[None]:
    """Each function of SCOPES wrapped in a `record_function` named after it, for this block only."""
    import importlib

    undo = []
    for target, label in SCOPES.items():
        module, _, attr = target.partition(":")
        owner: object = importlib.import_module(module)
        *path, name = attr.split(".")
        for p in path:
            owner = getattr(owner, p)
        fn = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
        inner = fn.__func__ if isinstance(fn, staticmethod) else fn

        def scoped(*a, _fn=inner, _label=f"{label}|{attr}", **k):
            with torch.profiler.record_function(_label):
                return _fn(*a, **k)

        setattr(owner, name, staticmethod(scoped) if isinstance(fn, staticmethod) else scoped)
        undo.append((owner, name, fn))
    try:
        yield
    finally:
        for owner, name, fn in undo:
            setattr(owner, name, fn)


def machine_rates(threads: int) -> dict[str, float]:
    """This CPU's copy bandwidth (GB/s, a STREAM-like copy of 256 MB) and sgemm rate (GFLOP/s, at the
    colour MLP's shape and at 2048^2), best of a few."""
    torch.set_num_threads(threads)
    a, b = torch.rand(64 << 20), torch.empty(64 << 20)

    def best(fn, n: int = 5) -> float:
        fn()
        times = []
        for _ in range(n):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    copy = 2 * a.numel() * 4 / best(lambda: b.copy_(a)) / 1e9
    x, w = torch.rand(32768, 64), torch.rand(64, 64)
    mlp = 2 * 32768 * 64 * 64 / best(lambda: x @ w, 20) / 1e9
    m = torch.rand(2048, 2048)
    big = 2 * 2048**3 / best(lambda: m @ m) / 1e9
    return {"copy_GBps": copy, "sgemm_mlp_GFLOPs": mlp, "sgemm_2048_GFLOPs": big}


def part_of(event) -> str:
    """The part of the step an op belongs to: its innermost scope's, the backward, or the optimiser."""
    if event.name.startswith("autograd::engine::evaluate_function"):
        return "backward"
    p, inside_flip = event, False
    while p is not None:
        if "|" in p.name:
            label = p.name.split("|")[0]
            if label != "render_rays":
                return label
            query = next((c for c in p.cpu_children if "|GridField.query" in c.name), None)
            return "sampling" if query is None or event.time_range.start < query.time_range.start else "compositing"
        if p.name.startswith("Optimizer."):
            inside_flip = any("|Flip.after_step" in q.name for q in ancestors(p))
            return "Flip hooks" if inside_flip else "optimiser"
        p = p.cpu_parent
    return "other"


def ancestors(event):
    while event is not None:
        yield event
        event = event.cpu_parent


def profile_case(scene: str, preset: str, res: int, threads: int) -> dict:
    from flipviz.training.config import preset_config
    from flipviz.training.setup import load_scene_for
    from flipviz.training.trainer import Trainer

    torch.set_num_threads(threads)
    data = {"data": LEGO} if scene == "lego" else {}
    with tempfile.TemporaryDirectory() as tmp:
        cfg = preset_config(
            preset, scene=scene, res=res, no_rrd=True, images_every=0, checkpoint_every=0, out=Path(tmp) / "r",
            mirror_plane="official", **data,
        )  # fmt: skip
        trainer = Trainer(cfg, load_scene_for(cfg))
        windows: dict[str, dict] = {}
        for name, (first, last) in WINDOWS.items():
            while trainer.step < first:
                trainer._train_step()
            timed = wall_per_step(trainer, (last - first) // 2)  # ms a step takes with no profiler
            steps = last - trainer.step
            with scopes(), torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
                while trainer.step < last:
                    trainer._train_step()
            windows[name] = breakdown(prof, steps, timed) | sizes(trainer)
        trainer.close()
    return {"scene": scene, "preset": preset, "res": res, "threads": threads, "windows": windows}


def wall_per_step(trainer, steps: int) -> float:
    t = time.perf_counter()
    for _ in range(steps):
        trainer._train_step()
    return (time.perf_counter() - t) / steps * 1e3


def sizes(trainer, steps: int = 3) -> dict:
    """What a step looks up, over `steps` more steps: rays, samples, occupied samples (P), coloured
    samples (K), distinct grid voxels touched, and the grid's size."""
    field, seen = trainer.model.field, defaultdict(list)
    corners, color = field.corners, field._color

    def counted_corners(x):
        c = corners(x)
        seen["occupied_samples"].append(len(x))
        seen["voxels_touched"].append(int(torch.unique(c[0]).numel()))
        return c

    def counted_color(c, d):
        seen["coloured_samples"].append(len(d))
        return color(c, d)

    field.corners, field._color = counted_corners, counted_color
    try:
        for _ in range(steps):
            trainer._train_step()
    finally:
        del field.corners, field._color
    z, y, x = field.resolution
    n = trainer.model.cfg.n_samples
    mlp = [m.weight.shape[1] for m in field.rgbnet if hasattr(m, "weight")]  # each layer's inputs
    return {k: sum(v) / steps for k, v in seen.items()} | {
        "samples": trainer.cfg.engine.batch_rays * n, "voxels": z * y * x, "grid": [x, y, z],
        "channels": 1 + field.feat_grid.shape[-1], "mlp": mlp,
    }  # fmt: skip


def breakdown(prof, steps: int, wall_ms: float) -> dict:
    """ms per step of each part, and of the backward's ops, over a profiled window (ops timed under the
    profiler); `wall_ms`: a step's time without the profiler."""
    parts: dict[str, float] = defaultdict(float)
    backward: dict[str, float] = defaultdict(float)
    for e in prof.events():
        if "|" in e.name or e.name.startswith("Optimizer.") or not is_top_op(e):
            continue
        ms = e.cpu_time_total / 1e3 / steps
        part = part_of(e)
        parts[part] += ms
        if part == "backward":
            backward[e.name.split(": ")[-1]] += ms
    return {
        "ms_per_step": wall_ms,
        "ms_in_ops": sum(parts.values()),
        "parts": dict(sorted(parts.items(), key=lambda kv: -kv[1])),
        "backward_ops": dict(sorted(backward.items(), key=lambda kv: -kv[1])[:12]),
    }


def is_top_op(event) -> bool:
    """An op no other op encloses (scopes and the optimiser's step markers are not ops)."""
    p = event.cpu_parent
    while p is not None:
        if "|" not in p.name and not p.name.startswith("Optimizer."):
            return False
        p = p.cpu_parent
    return True


# backward ops -> the forward part they belong to (the rest: the per-sample chain)
BACKWARD_GATHERS = ("IndexSelectBackward", "BmmBackward", "IndexBackward", "IndexPutBackward", "ViewBackward")
BACKWARD_MLP = ("AddmmBackward", "MmBackward", "ReluBackward", "SigmoidBackward", "SoftplusBackward", "TBackward")
GROUPS = {  # a window's parts -> what the floor is computed for
    "per-sample chain (sampling, occupancy, compositing, objective)": (
        "sampling", "occupancy", "compositing", "objective", "regularisers (TV, entropy)"),
    "gathers (trilinear lookups)": ("gathers",),
    "MLPs (colour, beta)": ("density & colour MLP",),
    "grid update (gradient buffers, Adam)": ("optimiser",),
}  # fmt: skip


def grouped(window: dict) -> dict[str, float]:
    """A window's ms per step in the GROUPS, with each backward op added to the forward part it undoes."""
    out = {g: sum(window["parts"].get(p, 0.0) for p in parts) for g, parts in GROUPS.items()}
    names = list(GROUPS)
    for op, ms in window["backward_ops"].items():
        g = names[1] if op.startswith(BACKWARD_GATHERS) else names[2] if op.startswith(BACKWARD_MLP) else names[0]
        out[g] += ms
    rest = window["parts"].get("backward", 0.0) - sum(window["backward_ops"].values())  # ops past the top 12
    out[names[0]] += rest
    return out


def floors(w: dict, rates: dict) -> dict[str, float]:
    """ms per step each group needs at the measured rates: bytes / copy bandwidth, FLOPs / sgemm rate.

    per-sample chain: about 16 floats a sample written and read again, forward and backward (t, x, the
      occupancy lookup, sigma, tau, alpha, T, w, their gradients);
    gathers: 8 corners a sample (index 8 B, weight 4 B) and their rows (4 B a channel), read forward and
      scattered backward, for the occupied samples (density) and the coloured ones (features);
    MLPs: 2 FLOPs a weight a coloured sample, 3x for forward and backward;
    grid update: the dense gradient zeroed and filled, and Adam reading parameter, gradient and two
      moments and writing three (8 x 4 B a value); sparse: the same on the voxels the batch touched."""
    bw, mlp = rates["copy_GBps"] * 1e9, rates["sgemm_mlp_GFLOPs"] * 1e9
    weights = sum(a * b for a, b in zip(w["mlp"], w["mlp"][1:] + [4]))
    chain = 2 * 16 * 4 * w["samples"]
    gather = 2 * 8 * (w["occupied_samples"] * (12 + 4) + w["coloured_samples"] * (12 + 4 * (w["channels"] - 1)))
    values = w["voxels"] * w["channels"]
    return {
        list(GROUPS)[0]: chain / bw * 1e3,
        list(GROUPS)[1]: gather / bw * 1e3,
        list(GROUPS)[2]: 3 * 2 * weights * w["coloured_samples"] / mlp * 1e3,
        list(GROUPS)[3]: 8 * 4 * values / bw * 1e3,
        "grid update, sparse (the touched voxels only)": 8 * 4 * w["voxels_touched"] * w["channels"] / bw * 1e3,
    }


def markdown(results: dict) -> str:
    r = results["machine"]
    lines = [
        "# A training step, part by part (studies/profile_step.py)",
        "",
        f"Machine: copy {r['copy_GBps']:.1f} GB/s, sgemm {r['sgemm_mlp_GFLOPs']:.0f} GFLOP/s at the MLP's shape "
        f"(32768 x 64 x 64), {r['sgemm_2048_GFLOPs']:.0f} at 2048^2; {results['threads']} threads.",
        "",
    ]
    for name, case in results["cases"].items():
        for wname, w in case["windows"].items():
            lines += [f"## {name}, {wname} ({w['ms_per_step']:.1f} ms a step; in ops {w['ms_in_ops']:.1f} "
                      f"under the profiler)", "",
                      f"{w['samples']} samples, {w['occupied_samples']:.0f} occupied, {w['coloured_samples']:.0f} "
                      f"coloured; grid {'x'.join(map(str, w['grid']))} ({w['voxels']:,} voxels, "
                      f"{w['voxels_touched']:.0f} touched a step)", "",
                      "| part | ms / step |", "|---|---|"]  # fmt: skip
            lines += [f"| {p} | {ms:.2f} |" for p, ms in w["parts"].items()]
            lines += ["", "| backward op | ms / step |", "|---|---|"]
            lines += [f"| {p} | {ms:.2f} |" for p, ms in w["backward_ops"].items()]
            floor, got = floors(w, r), grouped(w)
            lines += ["", "| group (forward + backward) | ms / step | floor ms | x floor |", "|---|---|---|---|"]
            for g, ms in got.items():
                lines.append(f"| {g} | {ms:.2f} | {floor[g]:.3f} | {ms / max(floor[g], 1e-9):.0f} |")
            sparse = "grid update, sparse (the touched voxels only)"
            lines += [f"| {sparse} | | {floor[sparse]:.3f} | |", ""]
    return "\n".join(lines)


def main(args: Args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    rates = machine_rates(args.threads)
    print(json.dumps(rates, indent=1), flush=True)
    results = {"machine": rates, "threads": args.threads, "cases": {}}
    for name in args.cases:
        results["cases"][name] = profile_case(*CASES[name], args.threads)
        print(name, json.dumps(results["cases"][name]["windows"], indent=1), flush=True)
    (args.out / "profile.json").write_text(json.dumps(results, indent=1))
    (args.out / "README.md").write_text(markdown(results))


if __name__ == "__main__":
    main(tyro.cli(Args))
