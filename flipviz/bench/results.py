"""The bench's results on disk and the selections its tables and figures make of them.

Each run writes <out>/runs/<key>/result.json (status "ok" or "failed", its metrics and labels).
"""

from __future__ import annotations

import json
from pathlib import Path

from flipviz.bench.paper_numbers import paper_row

RESULT_FILE = "result.json"
STARTED_FILE = "started.json"
ABLATION = ((False, False), (True, False), (False, True), (True, True))  # (BA, U), Table II order


def read_json(path: Path) -> dict:
    """A run's JSON file (result.json, started.json) as a dict; {} when it is missing or unreadable."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def read_result(run_dir: Path) -> dict | None:
    """The run's result.json, or None when it has none (not run, killed, or unreadable)."""
    return read_json(Path(run_dir) / RESULT_FILE) or None


def ok_rows(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r.get("status") == "ok"]


def scenes(rows: list[dict]) -> list[str]:
    """The scenes of `rows`, in their first order."""
    return list(dict.fromkeys(r["scene"] for r in rows))


def main_rows(rows: list[dict], scene: str, method: str) -> list[dict]:
    """Table III runs: the method with its default flags (BA and U on where it has them)."""
    return [r for r in ok_rows(rows) if r["scene"] == scene and r["method"] == method and r.get("default_flags", True)]


def ablation_rows(rows: list[dict], scene: str, ba: bool, u: bool) -> list[dict]:
    """Table II runs of one (BA, U) cell."""
    return [
        r
        for r in ok_rows(rows)
        if r["scene"] == scene and r["method"] in ("flip", "flip+u") and r["ba"] == ba and r["uncertainty"] == u
    ]


def paper_scene(rows: list[dict], scene: str) -> str | None:
    """The paper's row name if `scene` was read from a folder with a NeRF-synthetic name."""
    folder = next((r.get("data") for r in rows if r["scene"] == scene), "")
    return paper_row(scene) if folder else None
