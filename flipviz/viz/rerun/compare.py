"""Runs' Rerun recordings side by side in one viewer: `flipviz compare RUN_A RUN_B [...]`.

Each run's recording (its `recording*.rrd`, resumed parts included) is read chunk by chunk
(`rerun.chunk.RrdReader`) and re-rooted under one entity prefix per run, `/<label>/world/...`,
`/<label>/views/...`, `/<label>/curves/...`, into one new recording with one blueprint: a column
per run (3D scene, test renders with their errors, test PSNR) and, below, the runs' test PSNR and
mirrored-pose errors on shared axes. The step timeline is shared, so scrubbing moves all runs.
The merged file is written whole or not at all; `--serve` also streams it to a local web viewer
bound to 127.0.0.1.
"""

from __future__ import annotations

import re
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import rerun as rr
import rerun.blueprint as rrb
import tyro

from flipviz.errors import UserError
from flipviz.files import atomic_path, free_bytes, need_space
from flipviz.viz.rerun.blueprint import STEP, entity_name

APP_ID = "flipviz-compare"


@dataclass
class CompareConfig:
    """Open runs' Rerun recordings together, side by side, in one viewer."""

    runs: Annotated[list[Path], tyro.conf.Positional]
    """Two to four run folders (or .rrd files)."""
    out: Path = Path("compare.rrd")
    """The merged recording to write (open it with `rerun compare.rrd`)."""
    serve: bool = False
    """Also serve it in a local Rerun web viewer (127.0.0.1) and print its URL; Ctrl-C to quit."""


def recordings_of(run: Path) -> list[Path]:
    """The .rrd files of a run folder (recording.rrd, then recording.1.rrd, ... of resumed parts)."""
    run = Path(run)
    if run.is_file() and run.suffix == ".rrd":
        return [run]
    files = sorted(run.glob("recording*.rrd"), key=lambda p: (len(p.name), p.name)) if run.is_dir() else []
    if not files:
        raise UserError(f"{run} holds no Rerun recording (recording.rrd); was it trained with --no-rrd?")
    return files


def run_labels(runs: list[Path]) -> list[str]:
    """One short, unique entity prefix per run: its folder name, made safe (A_, B_ prefixes if equal)."""
    names = [entity_name((p.parent if p.suffix == ".rrd" else p).name) for p in map(Path, runs)]
    if len(set(names)) < len(names):
        names = [f"{chr(65 + i)}_{n}" for i, n in enumerate(names)]
    return names


def merged_chunks(runs: list[Path]) -> tuple[list, list[str], dict[str, list[str]]]:
    """All runs' chunks re-rooted under their labels; the labels; each label's test view names."""
    from rerun.chunk import RrdReader

    chunks, tests = [], {}
    labels = run_labels(runs)
    for label, run in zip(labels, runs):
        names: set[str] = set()
        for path in recordings_of(run):
            try:
                stream = RrdReader(str(path)).stream()
                for chunk in stream:
                    ent = chunk.entity_path
                    if ent.startswith("/__"):  # recording properties: the merged file has its own
                        continue
                    if m := re.match(r"^/views/test/([^/]+)/render$", ent):
                        names.add(m.group(1))
                    chunks.append(chunk.with_entity_path(f"/{label}{ent}"))
            except Exception as e:  # truncated or foreign file: one line
                raise UserError(f"cannot read the recording {path} ({type(e).__name__}: {e})".splitlines()[0]) from None
        tests[label] = sorted(names)
    return chunks, labels, tests


def compare_blueprint(labels: list[str], tests: dict[str, list[str]]) -> rrb.Blueprint:
    """A column per run (3D scene, test render | error grid, its test PSNR); shared curves below."""
    columns = []
    for label in labels:
        grid = rrb.Grid(
            contents=[
                rrb.Spatial2DView(origin=f"/{label}/views/test/{n}/{part}", name=f"{n} {part}")
                for n in tests[label]
                for part in ("render", "error")
            ],
            grid_columns=4,
            name="test: render | error",
        )
        columns.append(
            rrb.Vertical(
                rrb.Spatial3DView(origin=f"/{label}/world", name=f"{label}: scene"),
                grid,
                row_shares=[1.0, 1.4],
                name=label,
            )
        )
    shared = rrb.Horizontal(
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{label}/curves/test/**" for label in labels], name="test PSNR (dB), all runs"
        ),
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{label}/curves/train/psnr" for label in labels], name="training PSNR (dB)"
        ),
        rrb.TimeSeriesView(
            origin="/",
            contents=[f"/{label}/curves/mirror/rot_err_deg/**" for label in labels],
            name="mirror rotation error (deg)",
        ),
    )
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*columns), shared, row_shares=[3.0, 1.0]),
        rrb.TimePanel(timeline=STEP, state="collapsed", play_state="following"),  # at the runs' last step
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def write_comparison(runs: list[Path], out: Path, grpc_url: str | None = None) -> tuple[Path, list[str]]:
    """Merge the runs' recordings into `out` (and stream them to `grpc_url`); returns it and the labels."""
    if not 2 <= len(runs) <= 4:
        raise UserError(f"flipviz compare takes 2 to 4 runs, got {len(runs)}")
    chunks, labels, tests = merged_chunks(runs)
    blueprint = compare_blueprint(labels, tests)
    try:  # about the inputs' size: a full disk fails inside Rerun's writer, with no readable file
        need_space(out, 1.1 * sum(f.stat().st_size for r in runs for f in recordings_of(Path(r))) + 8e6, str(out))
        with atomic_path(out) as tmp:
            rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
            sinks = [rr.FileSink(str(tmp))] + ([rr.GrpcSink(grpc_url)] if grpc_url else [])
            rec.set_sinks(*sinks, default_blueprint=blueprint)
            rec.send_recording_name(" vs ".join(labels))
            rr.send_chunks(chunks, recording=rec)
            try:
                rec.flush(timeout_sec=30.0)
            finally:
                rec.disconnect()
    except RuntimeError as e:  # the file writer failed (the disk filled up meanwhile); no partial file is left
        raise UserError(
            f"cannot write {out}: {str(e).splitlines()[0]} ({free_bytes(out) / 1e6:.0f} MB free on that disk)"
        ) from None
    except OSError as e:
        raise UserError(f"cannot write {out}: {e.strerror or e}") from None
    return Path(out), labels


def run_compare(cfg: CompareConfig) -> int:
    """`flipviz compare`: write the merged recording; with --serve, show it until Ctrl-C."""
    viewer = None
    if cfg.serve:
        from flipviz.viz.rerun.viewer import RerunWebViewer

        viewer = RerunWebViewer.start()
    try:
        out, labels = write_comparison(cfg.runs, cfg.out, viewer.grpc_url if viewer else None)
        print(f"wrote {out} ({', '.join(labels)}); open it with: rerun {out}")
        if viewer is not None:
            import threading

            print(f"Rerun web viewer: {viewer.url}  (Ctrl-C to quit)", flush=True)
            threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        if viewer is not None:
            viewer.stop()
    return 0
