"""The bench's reports: results.csv, results.json and table.md (paper Table III and Table II)."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict
from pathlib import Path

from flipviz.bench.config import BenchConfig, parse_configs, parse_methods
from flipviz.bench.paper_numbers import METHOD_LABELS, METHOD_ORDER, TABLE2, TABLE3
from flipviz.bench.results import ABLATION, ablation_rows, main_rows, ok_rows, paper_scene, scenes
from flipviz.files import write_json, write_text
from flipviz.training.config import EvalConfig

CSV_FIELDS = (
    "scene",
    "method",
    "config",
    "ba",
    "uncertainty",
    "psnr",
    "ssim",
    "lpips",
    "iou",
    "psnr_object",
    "depth_abs",
    "mirror_angle_deg",
    "within_30",
    "plane_confidence",
    "mirrors_trained",
    "mirrors_dropped_at",
    "field_restarted_at",
    "kept_mirrors",
    "n_mirrors",
    "plane_error_deg",
    "plane_error_offset",
    "refined_error_deg",
    "refined_error_offset",
    "reused_from",
    "train_seconds",
    "wall_seconds",
    "steps",
    "res",
    "seed",
    "field",
    "device",
    "status",
    "error",
    "key",
    "run_id",
    "data",
    "flipviz_version",
    "torch_version",
    "numpy_version",
)
PLANE_KEYS = {  # results.csv column: the key in metrics.json's "plane" (Trainer.report)
    "plane_confidence": "confidence",
    "mirrors_trained": "trained",
    "mirrors_dropped_at": "dropped_at",
    "field_restarted_at": "restarted_at",
    "kept_mirrors": "kept_mirrors",
    "n_mirrors": "n_mirrors",
    "plane_error_deg": "error_deg",
    "plane_error_offset": "error_offset",
    "refined_error_deg": "refined_error_deg",
    "refined_error_offset": "refined_error_offset",
}
METRICS = ("psnr", "ssim", "lpips")
STRUCTURE = ("iou", "psnr_object", "depth_abs")  # training/evaluate.py: what the object itself scores
DIGITS = {"psnr": 2, "ssim": 3, "lpips": 3, "iou": 3, "psnr_object": 2, "depth_abs": 3}
LABELS = {
    "psnr": "PSNR",
    "ssim": "SSIM",
    "lpips": "LPIPS",
    "iou": "silhouette IoU",
    "psnr_object": "PSNR in the object",
    "depth_abs": "depth error",
}


def metric(r: dict, key: str):
    """A run's value of `key`: top level (psnr, ssim, lpips), its structure scores, its coverage."""
    if key in r:
        return r[key]
    m = r.get("metrics") or {}
    if key in ("mirror_angle_deg", "within_30"):
        cov = m.get("coverage") or {}
        return cov.get("mean_angle_deg" if key == "mirror_angle_deg" else key)
    if key in PLANE_KEYS:  # Flip runs: the auto plane's confidence and use; its error before and after training
        return (m.get("plane") or {}).get(PLANE_KEYS[key])
    return m.get(key)


def flat_row(r: dict) -> dict:
    """One results.csv row of a run's result."""
    tc, v = r.get("train_config", {}), r.get("versions", {})
    row = {k: metric(r, k) for k in CSV_FIELDS}
    row.update(
        res=tc.get("res"),
        seed=tc.get("seed"),
        field=tc.get("field"),
        device=tc.get("device"),
        flipviz_version=v.get("flipviz"),
        torch_version=v.get("torch"),
        numpy_version=v.get("numpy"),
    )
    if row["lpips"] is None and r.get("status") == "ok":
        row["lpips"] = "unavailable"
    return row


def _mean(xs: list) -> float | str | None:
    """Mean of numbers; "unavailable" if any value is a string (LPIPS without weights)."""
    if not xs:
        return None
    if any(isinstance(x, str) or x is None for x in xs):
        return "unavailable"
    return sum(xs) / len(xs)


def _fmt(x, metric: str) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return "n/a"
    return "nan" if math.isnan(x) else f"{x:.{DIGITS[metric]}f}"


def headline_metrics(rows: list[dict]) -> list[str]:
    """Table III's columns: PSNR, then the object's own scores beside it (those some run has: lego has
    no true depth), then the paper's SSIM and LPIPS."""
    have = [k for k in STRUCTURE if any(metric(r, k) is not None for r in ok_rows(rows))]
    return ["psnr", *have, "ssim", "lpips"]


def _mean_of(rows: list[dict], key: str) -> float | str | None:
    """The mean of `key` over runs: the paper's metrics as they are (LPIPS may be "unavailable"), the
    object's scores over the runs that have a finite one."""
    if key in METRICS:
        return _mean([r[key] for r in rows])
    return _mean([v for r in rows if (v := metric(r, key)) is not None and math.isfinite(v)])


def table3(rows: list[dict], methods: list[str], n_configs: int) -> str:
    """Markdown of the paper's Table III, a row per scene and method (mean over configurations), with the
    object's own scores (silhouette IoU, PSNR in the object, depth error) beside PSNR; then the mean
    over scenes and the paper's mean."""
    names, keys = scenes(rows), headline_metrics(rows)
    head = ["Scene", "Method", *(LABELS[k] for k in keys)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    ours: dict[tuple, list] = {}
    papers: dict[tuple, list] = {}
    for scene in names:
        prow = paper_scene(rows, scene)
        label = scene + (f" ({prow})" if prow and prow.lower() != scene.lower() else "")
        blank = {"psnr": metric_blank(rows, scene, "blank_psnr"), "ssim": metric_blank(rows, scene, "blank_ssim")}
        lines.append(
            f"| {label} | white image | " + " | ".join(_fmt(blank.get(k), k) if k in blank else "" for k in keys) + " |"
        )
        for m in methods:
            rs = main_rows(rows, scene, m)
            cells = [label, METHOD_LABELS[m] + (f" †{len(rs)}/{n_configs}" if rs and len(rs) < n_configs else "")]
            for key in keys:
                v = _mean_of(rs, key)
                if v is not None:
                    ours.setdefault((key, m), []).append(v)
                cell = _fmt(v, key)
                if prow and key in METRICS:
                    p = TABLE3[key][prow][m]
                    papers.setdefault((key, m), []).append(p)
                    cell += f" ({p:.{DIGITS[key]}f})"
                cells.append(cell)
            lines.append("| " + " | ".join(cells) + " |")
    all_paper = all(paper_scene(rows, s) for s in names)
    for m in methods if len(names) > 1 else ():  # the mean over scenes
        cells = ["**Mean**", METHOD_LABELS[m]]
        for key in keys:
            cell = _fmt(_mean(ours.get((key, m), [])), key)
            if all_paper and papers.get((key, m)):
                cell += f" ({_fmt(_mean(papers[(key, m)]), key)})"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    for m in methods:
        paper = [f"({TABLE3[k]['Mean'][m]:.{DIGITS[k]}f})" if k in METRICS else "" for k in keys]
        lines.append(f"| Paper mean (8 scenes) | {METHOD_LABELS[m]} | " + " | ".join(paper) + " |")
    return "\n".join(lines)


def metric_blank(rows: list[dict], scene: str, key: str) -> float | None:
    """An all-white image's score (blank_psnr, blank_ssim) on the scene's unobserved views, mean over its
    configurations (each run scores it on its own test views: the same for every method of a configuration)."""
    per_config = {
        r["config"]: metric(r, key) for r in ok_rows(rows) if r["scene"] == scene and metric(r, key) is not None
    }
    return sum(per_config.values()) / len(per_config) if per_config else None


def table2(rows: list[dict]) -> str:
    """Markdown like the paper's Table II: Flip+U with bundle adjustment / uncertainty on and off."""
    lines = [
        "| bundle adjustment | uncertainty | PSNR | SSIM | LPIPS | runs | paper PSNR | paper SSIM | paper LPIPS |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for ba, u in ABLATION:
        per_scene = {m: [] for m in METRICS}
        n = 0
        for scene in scenes(rows):
            rs = ablation_rows(rows, scene, ba, u)
            n += len(rs)
            for m in METRICS:
                v = _mean([r[m] for r in rs])
                if v is not None:
                    per_scene[m].append(v)
        p = TABLE2[(ba, u)]
        tick = lambda b: "✓" if b else "-"  # noqa: E731
        ours = " | ".join(_fmt(_mean(per_scene[m]), m) for m in METRICS)
        paper = f"{p['psnr']:.3f} | {p['ssim']:.3f} | {p['lpips']:.3f}"
        lines.append(f"| {tick(ba)} | {tick(u)} | {ours} | {n} | {paper} |")
    return "\n".join(lines)


def gain(rows: list[dict], scene: str, config: int, key: str = "psnr") -> float | None:
    """Flip+U - B/L of one configuration (None unless both ran)."""
    a = [r for r in main_rows(rows, scene, "flip+u") if r["config"] == config]
    b = [r for r in main_rows(rows, scene, "bl") if r["config"] == config]
    if not a or not b or metric(a[0], key) is None or metric(b[0], key) is None:
        return None
    return metric(a[0], key) - metric(b[0], key)


def per_config_table(rows: list[dict], methods: list[str]) -> str:
    """PSNR per configuration, the gain Flip+U - B/L (PSNR, and PSNR in the object), and how well that
    configuration's mirrored cameras cover its unobserved views (geometry/coverage.py)."""
    both = "bl" in methods and "flip+u" in methods
    head = ["Scene", "Config"] + [METHOD_LABELS[m] for m in methods]
    if both:
        head += [
            "gain Flip+U - B/L",
            "gain in the object",
            "angle to nearest mirror (deg)",
            "tests within 30 deg",
            "plane confidence (Flip+U)",
            "plane error before -> after training (Flip+U)",
            "mirrors kept (Flip+U)",
        ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene in scenes(rows):
        for n in sorted({r["config"] for r in rows if r["scene"] == scene}):
            cells = [scene, str(n)]
            for m in methods:
                rs = [r for r in main_rows(rows, scene, m) if r["config"] == n]
                cells.append(_fmt(rs[0]["psnr"], "psnr") if rs else "-")
            if both:
                g, go = gain(rows, scene, n), gain(rows, scene, n, "psnr_object")
                cov = coverage_run(rows, scene, n)
                cells += [f"{g:+.2f}" if g is not None else "-", f"{go:+.2f}" if go is not None else "-"]
                cells += (
                    [f"{metric(cov, 'mirror_angle_deg'):.1f}", f"{metric(cov, 'within_30'):.0%}"] if cov else ["-", "-"]
                )
                fu = next((r for r in main_rows(rows, scene, "flip+u") if r["config"] == n), None)
                cells += [plane_cell(fu), plane_error_cell(fu), kept_cell(fu)]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def coverage_run(rows: list[dict], scene: str, config: int) -> dict | None:
    """The run whose coverage a configuration reports: its Flip+U run's (the mirrors it was given: with
    --mirror-plane auto, B/L's would-be mirrors use another plane), else any run's."""
    have = [
        r for r in ok_rows(rows) if r["scene"] == scene and r["config"] == config and metric(r, "within_30") is not None
    ]
    return next(
        (r for r in have if r["method"] == "flip+u" and r.get("default_flags", True)), have[0] if have else None
    )


def kept_cell(r: dict | None) -> str:
    """How many of a Flip+U run's mirrored views the agreement gate kept to the end ("-": runs from before
    per-mirror verdicts, whose gate kept all or none: the plane column says which)."""
    kept, n = (metric(r, "kept_mirrors"), metric(r, "n_mirrors")) if r else (None, None)
    return f"{kept} of {n}" if kept is not None and n is not None else "-"


def plane_cell(r: dict | None) -> str:
    """The auto plane's confidence of a Flip+U run, and "dropped" when its mirrors were not trained (at
    setup, for the confidence) or "dropped at N" (by the agreement gate, at step N; ", restarted": the field
    then trained the inputs afresh, --after-drop restart)."""
    conf = metric(r, "plane_confidence") if r else None
    if conf is None:
        return "-"
    at, again = metric(r, "mirrors_dropped_at"), ", restarted" if metric(r, "field_restarted_at") is not None else ""
    dropped = (
        f" (dropped at {at}{again})"
        if at is not None
        else " (dropped)"
        if metric(r, "mirrors_trained") is False
        else ""
    )
    return f"{conf:.3f}{dropped}"  # 3 digits: 0.248 is below 0.25


def plane_error_cell(r: dict | None) -> str:
    """A Flip+U run's plane error against the scene's true plane, where it started -> where training left it."""
    deg, off = (metric(r, "plane_error_deg"), metric(r, "plane_error_offset")) if r else (None, None)
    if deg is None:
        return "-"
    before = f"{deg:.2f}° / {off:.3f}"
    if metric(r, "refined_error_deg") is None:
        return before + " (not refined)"
    return f"{before} -> {metric(r, 'refined_error_deg'):.2f}° / {metric(r, 'refined_error_offset'):.3f}"


def time_table(rows: list[dict], methods: list[str]) -> str:
    head = ["Scene"] + [METHOD_LABELS[m] for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene in scenes(rows):
        cells = [scene]
        for m in methods:
            ts = [r["train_seconds"] for r in main_rows(rows, scene, m) if r.get("train_seconds") is not None]
            cells.append(f"{sum(ts) / len(ts):.0f}" if ts else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def protocol_words(cfg: BenchConfig) -> str:
    """The protocol a bench's runs were scored in, as its tables name it (training/config.py: EvalConfig)."""
    return EvalConfig(cfg.eval_views, cfg.eval_tune_steps, cfg.eval_every).words()


def render_markdown(rows: list[dict], cfg: BenchConfig) -> str:
    methods = [m for m in METHOD_ORDER if m in parse_methods(cfg.methods)]
    configs = parse_configs(cfg.configs)
    n_ok = len(ok_rows(rows))
    failed = [r for r in rows if r.get("status") != "ok"]
    lpips_na = any(r.get("lpips") in (None, "unavailable") for r in ok_rows(rows))
    versions = next((r.get("versions") for r in ok_rows(rows) if r.get("versions")), {})
    parts = [
        "# flipviz bench: Just Flip, paper Table III" + (" and Table II" if cfg.ablation else ""),
        "",
        f"Settings: preset `{cfg.preset}`, field `{cfg.field}`"
        + (f" (grid {cfg.grid_res})" if cfg.grid_res else "")
        + f", {cfg.n_samples} samples/ray"
        + f", {cfg.res} px, {cfg.steps} steps of {cfg.batch_rays} rays, "
        f"seed {cfg.seed}, device `{cfg.device}`, "
        f"configurations {', '.join(map(str, configs))}. {n_ok}/{len(rows)} runs ok. "
        f"Versions: {', '.join(f'{k} {v}' for k, v in versions.items()) or 'n/a'}.",
        "",
        f"## Table III, {protocol_words(cfg)}: mean over configurations",
        "",
        "Cells: ours (paper). *white image*: PSNR and SSIM of an all-white image on the same views, what a"
        " render showing nothing scores. Whole-image PSNR rewards keeping unobserved space white, so the object's"
        " own scores stand beside it: *silhouette IoU* (rendered opacity > 0.5 against the true alpha), *PSNR in"
        " the object* (over the union of both silhouettes) and, for built-in scenes, *depth error* (mean"
        " |depth error| over the true silhouette, world units). The paper's numbers are shown for NeRF-synthetic"
        " scenes read from a folder; the paper trained vanilla NeRF for 50k iterations, so compare trends, not values."
        " †k/n: only k of n configurations finished."
        + (" LPIPS n/a: AlexNet/LPIPS weights were not available." if lpips_na else ""),
        "",
        table3(rows, methods, len(configs)),
        "",
    ]
    if cfg.ablation:
        parts += ["## Table II: ablation of Flip+U (mean over scenes and configurations)", "", table2(rows), ""]
    parts += [
        "## PSNR per configuration, and why a configuration gains or loses",
        "",
        "Coverage: the angle from each unobserved view to the nearest mirrored camera (about the object's centre), "
        "mean over the 8 views, and the share of views within 30 degrees of one.",
        "",
        per_config_table(rows, methods),
        "",
    ]
    parts += ["## Mean training time per run (s)", "", time_table(rows, methods), ""]
    if failed:
        parts += ["## Failed runs", ""]
        parts += [
            f"- `{r['key']}` ({r['scene']} {r['method']} cfg {r['config']}): {r.get('error', '')}" for r in failed
        ]
        parts.append("")
    return "\n".join(parts)


def read_table(out: Path) -> list[dict]:
    """The rows of a bench's results.csv (`write_reports`), each value the string written; [] when the bench
    wrote none."""
    table = Path(out) / "results.csv"
    return list(csv.DictReader(io.StringIO(table.read_text()))) if table.is_file() else []


def write_reports(out: Path, rows: list[dict], cfg: BenchConfig) -> None:
    """results.csv, results.json and table.md in `out`, each written atomically."""
    flat = [flat_row(r) for r in rows]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS)
    w.writeheader()
    w.writerows(flat)
    write_text(out / "results.csv", buf.getvalue())
    write_json(out / "results.json", {"bench": asdict(cfg), "runs": rows})
    write_text(out / "table.md", render_markdown(rows, cfg))
