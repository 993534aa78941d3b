"""Every numeric option of every command is bounded where it is read (flipviz/options.py, issue 44).

The cases are generated from the configs themselves: a new numeric flag without a `Range` fails the
first test, and gets its refusals checked by the second without anyone writing a line for it.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from flipviz import cli
from flipviz.bench import BenchConfig
from flipviz.options import Range, base_type, check_ranges, flag, is_numeric, options, range_of
from flipviz.training.config import TrainConfig
from flipviz.viz.app.app import AppConfig
from flipviz.viz.export.report import ReportConfig
from flipviz.viz.export.video import VideoConfig
from flipviz.viz.rerun.compare import CompareConfig

# command -> (its config class, the positional arguments it needs to parse)
COMMANDS = {
    "train": (TrainConfig, []),
    "app": (AppConfig, []),
    "bench": (BenchConfig, []),
    "video": (VideoConfig, ["run"]),
    "report": (ReportConfig, ["run"]),
    "compare": (CompareConfig, ["a", "b"]),
    "export-scene": (cli.ExportScene, ["chair", "out"]),
    "score": (cli.Score, ["run"]),
}


def numeric_options(cls: type) -> list[tuple[str, object]]:
    return [(name, hint) for name, _, hint in options(cls) if is_numeric(hint)]


def test_every_numeric_option_of_every_command_carries_its_range():
    found = {cmd: numeric_options(cls) for cmd, (cls, _) in COMMANDS.items()}
    assert len(found["train"]) >= 17 and len(found["app"]) >= len(found["train"]) + 4 and found["bench"]
    unbounded = [f"{cmd} {flag(name)}" for cmd, opts in found.items() for name, hint in opts if range_of(hint) is None]
    assert not unbounded, f"numeric options without a Range (flipviz/options.py): {unbounded}"
    # the walk reaches the groups' flat flags and their tyro names (DataConfig.path is --data)
    names = {name for name, _, _ in options(TrainConfig)}
    assert {"steps", "plane_lr", "data", "rrd"} <= names and "path" not in names


def bad_values(r: Range, whole: bool) -> list[str]:
    """Values outside `r`, as a user types them: NaN, infinities, below and above, zero, huge."""
    out = ["nan", "inf", "-inf", "1e30", "-1e30"]
    if math.isfinite(r.lo):
        out.append(str(r.lo - 1 if whole else r.lo - max(1e-3, abs(r.lo) * 1e-3)))
    if math.isfinite(r.hi):
        out.append(str(r.hi + 1 if whole else r.hi * 1.01 + 1e-3))
    if r.lo > 0:
        out.append("0")
    return [v for v in out if not r.holds(float(v))]  # inf and 1e30 are fine where hi is inf


CASES = [
    (cmd, name, value)
    for cmd, (cls, _) in COMMANDS.items()
    for name, hint in numeric_options(cls)
    for value in bad_values(range_of(hint) or Range(0, 0), base_type(hint) is int)
]


@pytest.mark.parametrize("cmd, name, value", CASES, ids=[f"{c}-{n}={v}" for c, n, v in CASES])
def test_a_value_outside_its_range_is_one_line_before_any_work(tmp_path, monkeypatch, capsys, cmd, name, value):
    """NaN, inf, negative, zero and huge values of every numeric flag: one line, exit 2, refused before the
    command does anything (it is never dispatched), and nothing left on disk."""
    monkeypatch.chdir(tmp_path)
    dispatched = []
    monkeypatch.setattr(cli, "_dispatch", lambda c: dispatched.append(c) or 0)
    cls, positional = COMMANDS[cmd]
    code = cli.main([cmd, *positional, flag(name), value])
    err = capsys.readouterr().err.strip()
    assert code == 2 and not dispatched, (code, err)
    assert len(err.splitlines()) == 1 and flag(name) in err, err
    assert not list(tmp_path.iterdir())


INSTANCES = {  # a config of each command, for the direct checks below
    "video": lambda: VideoConfig(runs=[Path("run")]),
    "report": lambda: ReportConfig(run=Path("run")),
    "compare": lambda: CompareConfig(runs=[Path("a"), Path("b")]),
    "export-scene": lambda: cli.ExportScene(scene="chair", out_dir=Path("out")),
    "score": lambda: cli.Score(run=Path("run")),
}


@pytest.mark.parametrize("cmd", list(COMMANDS))
def test_the_ends_of_every_range_are_accepted(cmd):
    """Each bound is itself a valid value: a Range that is off by one refuses what its flag's help allows."""
    cls = COMMANDS[cmd][0]
    for _, path, hint in options(cls):
        r = range_of(hint)
        for end in (r.lo, r.hi) if r else ():
            cfg = INSTANCES.get(cmd, cls)()
            group = cfg if len(path) == 1 else getattr(cfg, path[0])
            value = int(end) if base_type(hint) is int and math.isfinite(end) else end
            setattr(group, path[-1], (value,) if "tuple" in str(hint) else value)  # grid_res: a tuple
            check_ranges(cfg)
