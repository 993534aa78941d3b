"""The bench's report.html: table.md, the PSNR chart and the qualitative grids in one self-contained
page (images embedded; opens offline, see flipviz/viz/export/report.py)."""

from __future__ import annotations

from pathlib import Path

from flipviz.bench.config import BenchConfig
from flipviz.bench.figures import CHART_FILE, GAIN_FILE
from flipviz.files import write_text
from flipviz.viz.export.report import Figure, Section, file_uri, markdown, page

REPORT_FILE = "report.html"


def write_html_report(out: Path, cfg: BenchConfig) -> Path:
    """report.html in `out`, from the table.md and figures the bench wrote there."""
    text = (out / "table.md").read_text()
    title, _, body = text.partition("\n")
    sections = [Section("", markdown(body), anchor="tables")]
    if (out / CHART_FILE).is_file():
        sections.append(Section("PSNR by method", "", [Figure(file_uri(out / CHART_FILE), width="100%")]))
    if (out / GAIN_FILE).is_file():
        sections.append(Section("Gain against coverage", "", [Figure(file_uri(out / GAIN_FILE), width="640px")]))
    for grid in sorted(out.glob("grid_*.png")):
        scene = grid.stem.removeprefix("grid_")
        sections.append(Section(f"Unobserved views: {scene}", "", [Figure(file_uri(grid), width="100%")]))
    return write_text(out / REPORT_FILE, page(title.lstrip("# ").strip() or "flipviz bench", sections))
