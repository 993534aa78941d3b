"""The bench's figures: PSNR bar chart per method and scene, and a qualitative grid (paper Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flipviz.bench.config import BenchConfig, parse_methods
from flipviz.bench.paper_numbers import METHOD_LABELS, METHOD_ORDER, TABLE3
from flipviz.bench.results import main_rows, paper_scene, scenes
from flipviz.bench.tables import coverage_run, gain, metric

CHART_FILE = "psnr_chart.png"
GAIN_FILE = "gain_vs_coverage.png"
RENDERS_DIR = "test_renders"  # the trainer's <run>/test_renders/<view>.png and <view>_gt.png


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def psnr_chart(rows: list[dict], methods: list[str], path: Path) -> Path:
    """Grouped bars: PSNR per scene (and the mean) per method, std over configurations as error
    bars, the paper's value as a black tick where the scene is a NeRF-synthetic one."""
    plt = _plt()
    names = scenes(rows)
    groups = names + ["Mean"]
    width = 0.8 / max(1, len(methods))
    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(groups) * max(1, len(methods)) * 0.35 + 2), 3.6))
    colors = plt.get_cmap("tab10")
    for j, m in enumerate(methods):
        means, stds, paper = [], [], []
        for scene in names:
            vals = [r["psnr"] for r in main_rows(rows, scene, m) if r.get("psnr") is not None]
            means.append(float(np.mean(vals)) if vals else np.nan)
            stds.append(float(np.std(vals)) if len(vals) > 1 else np.nan)  # nan: no error bar
            prow = paper_scene(rows, scene)
            paper.append(TABLE3["psnr"][prow][m] if prow else np.nan)
        finite = [v for v in means if np.isfinite(v)]
        means.append(float(np.mean(finite)) if finite else np.nan)
        stds.append(np.nan)
        paper.append(float(np.mean(paper)) if np.isfinite(paper).all() else np.nan)  # all NeRF-synthetic
        x = np.arange(len(groups)) + (j - (len(methods) - 1) / 2) * width
        ax.bar(x, means, width, yerr=stds, capsize=2, label=METHOD_LABELS[m], color=colors(j))
        if np.isfinite(paper).any():
            ax.scatter(x, paper, marker="_", s=120, color="black", zorder=3, label="paper" if j == 0 else None)
    ax.set_xticks(np.arange(len(groups)), groups)
    ax.set_ylabel("PSNR (dB), unobserved views")
    ax.set_title("Mean over configurations")
    ax.legend(fontsize=7, ncol=min(6, len(methods) + 1), loc="upper center", bbox_to_anchor=(0.5, -0.1), frameon=False)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def gain_chart(rows: list[dict], path: Path) -> Path | None:
    """Each configuration's gain Flip+U - B/L against its mirrors' coverage of the unobserved views
    (mean angle to the nearest mirrored camera), a colour per scene: does flipping help where the
    mirrors land near the test views? Both gains: over the whole image (filled) and inside the object
    (hollow, joined to it), since whole-image PSNR also rewards white where nothing was seen."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.6, 3.8))
    colors = plt.get_cmap("tab10")
    drawn = False
    for i, scene in enumerate(scenes(rows)):
        pts = []
        for n in sorted({r["config"] for r in rows if r["scene"] == scene}):
            g, go = gain(rows, scene, n), gain(rows, scene, n, "psnr_object")
            run = coverage_run(rows, scene, n)
            if g is not None and run is not None:
                pts.append((metric(run, "mirror_angle_deg"), g, go, n))
        if pts:
            drawn = True
            x, y, yo, _ = zip(*pts)
            ax.scatter(x, y, color=colors(i), label=scene, s=30)
            obj = [(xi, yi, v) for xi, yi, v in zip(x, y, yo) if v is not None and np.isfinite(v)]
            if obj:
                ox, oy, ov = zip(*obj)
                ax.scatter(ox, ov, facecolors="none", edgecolors=colors(i), s=30)
                ax.vlines(ox, oy, ov, color=colors(i), lw=0.6, alpha=0.6)
            for xi, yi, _, n in pts:
                ax.annotate(str(n), (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7, color=colors(i))
    if not drawn:
        plt.close(fig)
        return None
    ax.scatter([], [], color="grey", s=30, label="whole image")
    ax.scatter([], [], facecolors="none", edgecolors="grey", s=30, label="inside the object")
    ax.axhline(0.0, color="black", lw=0.8)
    ax.set_xlabel("mean angle from a test view to the nearest mirrored camera (deg)")
    ax.set_ylabel("PSNR gain, Flip+U - B/L (dB)")
    ax.set_title("Gain per configuration (labels) against coverage", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_renders(out: Path, row: dict) -> list[tuple[str, Path, Path]]:
    """(view name, render, ground truth) of a run's unobserved views, in the protocol's order."""
    d = out / "runs" / row["key"] / RENDERS_DIR
    names = [v["name"] for v in row.get("per_view", [])] or sorted(
        p.stem for p in d.glob("*.png") if not p.stem.endswith("_gt")
    )
    found = [(n, d / f"{n}.png", d / f"{n}_gt.png") for n in names]
    return [f for f in found if f[1].is_file()]


def qualitative_grid(
    out: Path, rows: list[dict], scene: str, methods: list[str], n_views: int, path: Path
) -> Path | None:
    """Rows: ground truth, then each method; columns: the first `n_views` unobserved views of the
    lowest configuration that every method finished (else the lowest with any)."""
    plt = _plt()
    by_config: dict[int, dict[str, dict]] = {}
    for m in methods:
        for r in main_rows(rows, scene, m):
            if run_renders(out, r):
                by_config.setdefault(r["config"], {})[m] = r
    if not by_config:
        return None
    config = min(by_config, key=lambda n: (-len(by_config[n]), n))
    runs = by_config[config]
    ref = run_renders(out, next(iter(runs.values())))[:n_views]
    names = [n for n, _, _ in ref]
    shown = [m for m in methods if m in runs]
    nr, nc = 1 + len(shown), len(names)
    fig, axes = plt.subplots(nr, nc, figsize=(1.7 * nc + 0.6, 1.7 * nr), squeeze=False)
    for i, label in enumerate(["GT"] + [METHOD_LABELS[m] for m in shown]):
        renders = {n: (p, g) for n, p, g in (ref if i == 0 else run_renders(out, runs[shown[i - 1]]))}
        psnrs = {} if i == 0 else {v["name"]: v.get("psnr") for v in runs[shown[i - 1]].get("per_view", [])}
        for j, name in enumerate(names):
            ax = axes[i][j]
            ax.set_xticks([])
            ax.set_yticks([])
            p, g = renders.get(name, (None, None))
            img_path = g if i == 0 else p
            if img_path is not None and img_path.is_file():
                ax.imshow(plt.imread(str(img_path)), interpolation="nearest")
            if psnrs.get(name) is not None:
                ax.set_xlabel(f"{psnrs[name]:.1f} dB", fontsize=7, labelpad=1)
            if i == 0:
                ax.set_title(name, fontsize=8)
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(f"{scene}, configuration {config}: unobserved views", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(out: Path, rows: list[dict], cfg: BenchConfig) -> list[Path]:
    """psnr_chart.png and grid_<scene>.png in `out` (matplotlib, Agg backend)."""
    methods = [m for m in METHOD_ORDER if m in parse_methods(cfg.methods)]
    written = [psnr_chart(rows, methods, out / CHART_FILE)]
    if "bl" in methods and "flip+u" in methods and (g := gain_chart(rows, out / GAIN_FILE)) is not None:
        written.append(g)
    for scene in scenes(rows):
        g = qualitative_grid(out, rows, scene, methods, cfg.grid_views, out / f"grid_{scene}.png")
        if g is not None:
            written.append(g)
    return written
