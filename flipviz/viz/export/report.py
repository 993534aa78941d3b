"""Self-contained HTML pages that a browser opens offline, without Python or a server: `flipviz report
RUN` for a run, and the bench's report.html (flipviz/bench/report.py).

Every image is embedded as a data: URI and the page has no scripts or external links, so the one
file can be mailed to a class or opened from a USB stick. Markdown (the bench's table.md, the run's
summary) is turned into HTML by markdown-it-py; the page by a Jinja2 template (escaped).

A run's page: its settings and scores; where its cameras are (top view: inputs, unobserved tests,
the mirrored cameras at their initial and BA-refined poses, the mirror plane); each unobserved
view as render | ground truth | |error| | beta^2; each mirrored view as flipped image | render |
beta^2 (where the learned variance rises, the mirror disagrees with the model); an animated GIF
across the unobserved side.
"""

from __future__ import annotations

import base64
import io
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import jinja2
import numpy as np
import tyro
from markdown_it import MarkdownIt
from tqdm import tqdm

from flipviz.data.dataset import Plane
from flipviz.data.images import to_uint8
from flipviz.files import cannot_write, write_text
from flipviz.options import Range, check_ranges
from flipviz.training.config import METHOD_LABELS
from flipviz.viz import palette

if TYPE_CHECKING:
    from flipviz.training.saved_run import Run

TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{{ title }}</title>
<style>
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em; color: #222; }
h1 { font-size: 1.6em; } h2 { margin-top: 1.6em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.6em 0; }
th, td { border: 1px solid #ccc; padding: 3px 7px; text-align: right; } th { background: #f3f3f3; }
td:first-child, th:first-child { text-align: left; }
figure { margin: 0.8em 0; } figcaption { font-size: 0.85em; color: #555; }
img { max-width: 100%; image-rendering: auto; } .pixel img { image-rendering: pixelated; }
.note { font-size: 0.85em; color: #666; }
</style></head><body>
<h1>{{ title }}</h1>
{% for s in sections %}<section id="{{ s.anchor }}">
{% if s.heading %}<h2>{{ s.heading }}</h2>{% endif %}
{{ s.html | safe }}
{% for fig in s.figures %}<figure class="{{ fig.css }}">
<img alt="{{ fig.caption }}" src="{{ fig.uri }}" style="width: {{ fig.width }}">
{% if fig.caption %}<figcaption>{{ fig.caption }}</figcaption>{% endif %}</figure>{% endfor %}
</section>{% endfor %}
<p class="note">Written by flipviz; a self-contained page (images embedded, no scripts):
open it in any browser, offline.</p>
</body></html>
""")

_MD = MarkdownIt("commonmark").enable("table")
GIF_WIDTH = 120  # pixels of a panel of the page's animation (a page of a few MB)


@dataclass
class Figure:
    uri: str  # data: URI
    caption: str = ""
    width: str = "auto"  # CSS width, e.g. "100%"
    css: str = ""  # "pixel": upscale without smoothing (small renders)


@dataclass
class Section:
    heading: str
    html: str = ""
    figures: list[Figure] | None = None
    anchor: str = ""

    def __post_init__(self) -> None:
        self.figures = self.figures or []
        self.anchor = self.anchor or "".join(c if c.isalnum() else "-" for c in self.heading.lower())


def markdown(text: str) -> str:
    return _MD.render(text)


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def png_uri(img: np.ndarray) -> str:
    """A uint8 or [0, 1] float image as an embedded PNG."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img if img.dtype == np.uint8 else to_uint8(img)).save(buf, format="PNG", optimize=True)
    return data_uri(buf.getvalue(), "image/png")


def file_uri(path: Path) -> str:
    mime = {".png": "image/png", ".gif": "image/gif", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}[path.suffix.lower()]
    return data_uri(path.read_bytes(), mime)


def page(title: str, sections: list[Section]) -> str:
    return TEMPLATE.render(title=title, sections=sections)


# ---- a run's page ---------------------------------------------------------------------------------
@dataclass
class ReportConfig:
    """Write a run's self-contained HTML page (opens offline, no Python needed)."""

    run: Annotated[Path, tyro.conf.Positional]
    """Run folder (with its checkpoint.pt)."""
    out: Path | None = None
    """HTML file to write (default <run>/report.html)."""
    res: Annotated[int, Range(16, 2048)] = 200
    """Width in pixels of the renders on the page."""
    gif_frames: Annotated[int, Range(0, 10_000)] = 40
    """Frames of the animated path across the unobserved side (0: none)."""
    device: str | None = None


def refined_plane(metrics: dict) -> Plane | None:
    """The plane training ended with (metrics.json's plane.refined); None when not refined or not readable."""
    try:
        return Plane.from_dict(metrics["plane"]["refined"])  # Plane checks its point and normal
    except (KeyError, TypeError, ValueError):
        return None


def camera_map(setup, mirror_c2w: np.ndarray | None, refined: Plane | None = None) -> np.ndarray:
    """Top view of the run's cameras (x, y of their centres) with the mirror plane (the `refined` one, where
    training refined it, beside the one it started from), as an RGB image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 5.2), dpi=100)
    c = np.asarray(setup.sphere_center)
    kinds = (
        ("input", "inputs"),
        ("test", "unobserved tests"),
        ("mirror_init", "mirrored, initial"),
        ("mirror_true", "exact reflections"),
    )
    for kind, label in kinds:
        pts = np.array(
            [i.camera.center for i in setup.cameras if i.kind == kind and (kind != "mirror_init" or setup.plane)]
        )
        if len(pts):
            ax.scatter(pts[:, 0], pts[:, 1], s=28, color=palette.hex_color(palette.CAMERA[kind]), label=label)
    if mirror_c2w is not None:
        pts = mirror_c2w[:, :3, 3]
        ax.scatter(
            pts[:, 0],
            pts[:, 1],
            s=28,
            marker="x",
            color=palette.hex_color(palette.CAMERA["mirror"]),
            label="mirrored, BA-refined",
        )
    for plane, color, label, style in (
        (refined if refined is not None else setup.plane, palette.MIRROR_PLANE, "mirror plane", "-"),
        (setup.plane if refined is not None else None, palette.MIRROR_PLANE, "mirror plane at the start", ":"),
        (setup.true_plane, palette.TRUE_PLANE, "true plane", "--"),
    ):
        if plane is None:
            continue
        d = np.cross(np.asarray(setup.up), plane.normal)[:2]  # the plane's trace on the ground
        if np.linalg.norm(d) > 1e-6:
            d = d / np.linalg.norm(d) * 1.2 * setup.sphere_radius
            p = np.asarray(plane.point)[:2]
            ax.plot(
                [p[0] - d[0], p[0] + d[0]],
                [p[1] - d[1], p[1] + d[1]],
                color=palette.hex_color(color),
                label=label,
                linestyle=style,
            )
    ax.scatter([c[0]], [c[1]], marker="+", color="black", s=60, label="sphere centre")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title("cameras seen from above")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    from PIL import Image

    return np.asarray(Image.open(buf).convert("RGB"))


def _summary(run: Run, metrics: dict) -> str:
    cfg = run.cfg
    rows = [
        ("scene", run.scene.name),
        ("method", METHOD_LABELS[cfg.method]),
        (
            "views",
            f"configuration {run.split.config}"
            if run.split.config
            else f"inputs {cfg.data.inputs or '(capture split)'}",
        ),
        ("steps", run.step),
        ("resolution", f"{cfg.data.res} px"),
        ("field", cfg.engine.field),
        ("mirror plane", cfg.flip.mirror_plane),
        ("mirror pose", cfg.flip.mirror_pose),
        ("training time", f"{run.train_seconds:.0f} s on {cfg.engine.device}"),
    ]
    if "psnr" in metrics:
        rows += [("PSNR, unobserved views", f"{metrics['psnr']:.2f} dB"), ("SSIM", f"{metrics['ssim']:.3f}")]
    if "iou" in metrics:  # the object's own scores (training/evaluate.py)
        rows += [
            ("silhouette IoU", f"{metrics['iou']:.3f}"),
            ("PSNR inside the object", f"{metrics['psnr_object']:.2f} dB"),
        ]
    if "depth_abs" in metrics:
        rows.append(("depth error (world units)", f"{metrics['depth_abs']:.3f}"))
    plane = metrics.get("plane", {})
    if "refined_error_deg" in plane:  # the plane training refined: where it ended, and where it started
        err = f"{plane['refined_error_deg']:.3f} deg, offset {plane['refined_error_offset']:.4f}"
        rows.append(("plane error vs the true plane", f"{err} (refined; {plane['error_deg']:.2f} deg at the start)"))
    elif "error_deg" in plane:
        rows.append(
            ("plane error vs the true plane", f"{plane['error_deg']:.2f} deg, offset {plane['error_offset']:.3f}")
        )
    table = "| setting | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
    return markdown(table)


def run_page(cfg: ReportConfig) -> str:
    """The HTML of a run's page (renders its views with the run's final model)."""
    import json

    from flipviz.training.saved_run import open_run
    from flipviz.viz.camera_path import unobserved_path
    from flipviz.viz.export.video import GifFrames, GroundTruth, compose_row, render_frames

    run = open_run(cfg.run, cfg.device)
    views = tqdm(  # one bar over the views it renders (the camera path's frames have their own)
        total=len(run.split.tests) + len(run.mirror_views), desc="report: rendering views", unit="view", file=sys.stderr
    )
    mpath = run.run_dir / "metrics.json"
    metrics = json.loads(mpath.read_text()) if mpath.is_file() else {}
    setup = run.setup_event
    refined = refined_plane(metrics)
    label = f"{METHOD_LABELS[run.cfg.method]}, {run.scene.name}"
    sections = [
        Section("Run", _summary(run, metrics)),
        Section("Cameras", "", [Figure(png_uri(camera_map(setup, run.mirror_c2w(), refined)), width="640px")]),
    ]
    gt = GroundTruth.of_run(run)
    tests = []
    for v in run.split.tests:
        cam = v.camera.resized(cfg.res)
        tests.append(Figure(png_uri(compose_row(v.name, run.render(cam), gt(cam)))))
        views.update()
    sections.append(
        Section(
            "Unobserved views",
            markdown(
                "Render, ground truth (where known), |render - ground truth| and the learned variance beta^2 "
                "of each held-out "
                f"view: {label}."
            ),
            tests,
        )
    )
    mirrors = []
    for view, cam in zip(run.mirror_views, run.mirror_cameras()):
        out = run.render(cam)
        views.update()
        panels = [to_uint8(view.image), to_uint8(out["rgb"])]
        if out.get("beta2") is not None:
            panels.append(palette.colormap(out["beta2"], *palette.BETA2_RANGE))
        caption = f"{cam.name}: flipped input | render at the refined pose" + (
            " | beta^2 (0-0.1)" if len(panels) == 3 else ""
        )
        mirrors.append(
            Figure(png_uri(np.concatenate(panels, axis=1)), caption, width=f"{cfg.res * len(panels)}px", css="pixel")
        )
    if mirrors:
        sections.append(
            Section(
                "Mirrored views",
                markdown(
                    "Each flipped input, the model seen from its BA-refined pose and beta^2 there: "
                    "where beta^2 rises, the mirror "
                    "contradicts what the model learned from the other views (a symmetry-breaking part)."
                ),
                mirrors,
            )
        )
    views.close()
    if cfg.gif_frames > 0:
        small = GifFrames(step=1, max_panel=GIF_WIDTH)
        cams = [c.resized(min(cfg.res, GIF_WIDTH)) for c in unobserved_path(setup, cfg.gif_frames)]
        for _ in small.keep(render_frames([(label, run.render)], cams, gt, progress=True)):
            pass
        sections.append(Section("Across the unobserved side", "", [Figure(data_uri(small.gif_bytes(8), "image/gif"))]))
    return page(f"flipviz run {run.run_dir.name}", sections)


def write_run_report(cfg: ReportConfig) -> Path:
    check_ranges(cfg)
    out = cfg.out or Path(cfg.run) / "report.html"
    html = run_page(cfg)
    with cannot_write(out, "the report"):
        return write_text(out, html)
