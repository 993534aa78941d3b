"""The front door: README commands, CI script and the CLI's help and errors."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def test_ci_runs_the_readme_test_command() -> None:
    ci_line = [ln for ln in (ROOT / ".ci/run").read_text().splitlines() if ln.startswith("python3 -m venv")]
    assert len(ci_line) == 1
    readme = (ROOT / "README.md").read_text()
    assert ci_line[0] in readme, "README's test command and .ci/run differ"
    assert "torch==2.13.0" in ci_line[0], "the install must pin the CPU torch wheel"


@pytest.mark.slow
def test_app_help() -> None:
    r = _run("app.py", "--scene", "chair", "--help")
    assert r.returncode == 0, r.stderr
    for flag in ("--scene", "--method", "--config", "--port", "--host", "--data"):
        assert flag in r.stdout


@pytest.mark.slow
def test_cli_subcommands_help() -> None:
    r = _run("-m", "flipviz.cli", "--help")
    assert r.returncode == 0, r.stderr
    for sub in ("train", "app", "bench", "export-scene"):
        assert sub in r.stdout


@pytest.mark.parametrize("entry", [("-m", "flipviz.cli", "train"), ("app.py",)])
@pytest.mark.slow
def test_missing_dataset_is_a_one_line_error(tmp_path: Path, entry: tuple[str, ...]) -> None:
    r = _run(*entry, "--data", str(tmp_path / "nope"), "--steps", "1", "--no-rrd")
    assert r.returncode == 2
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("flipviz: error:"), r.stderr


def test_ctrl_c_during_setup_is_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    """Ctrl-C while the scene loads (before the training loop): one line, exit 130, no traceback."""
    from flipviz import cli
    from flipviz.training import trainer

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer.Trainer, "__init__", interrupted)
    code = cli.main(["train", "--scene", "chair", "--steps", "1", "--out", str(tmp_path / "run")])
    assert code == 130
    assert capsys.readouterr().err == "flipviz: interrupted (SIGINT)\n"


@pytest.mark.parametrize("entry, heavy", [("flipviz.cli", "torch"), ("app.py", "viser")])
@pytest.mark.slow
def test_ctrl_c_during_the_first_imports_is_one_line(entry: str, heavy: str) -> None:
    """A Ctrl-C lands while torch or viser is imported (seconds on a cold machine): one line, exit 130.
    The interrupt is raised by an import hook, at the import itself, so the test needs no timing."""
    hook = textwrap.dedent(f"""
        import builtins, runpy, sys
        real = builtins.__import__
        def interrupted(name, *a, **k):
            if name == {heavy!r}:
                raise KeyboardInterrupt
            return real(name, *a, **k)
        builtins.__import__ = interrupted
        sys.argv = [{entry!r}, *({"()" if entry == "app.py" else "('train',)"}), "--scene", "chair"]
        run = runpy.run_path if {entry!r}.endswith(".py") else runpy.run_module
        run({entry!r}, run_name="__main__")
    """)
    r = _run("-c", hook)
    assert r.returncode == 130 and r.stderr == "flipviz: interrupted (SIGINT)\n", (r.returncode, r.stderr[-2000:])
