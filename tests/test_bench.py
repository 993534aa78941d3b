"""`flipviz bench`: planning, resuming after a kill, failed runs, reports, the Ray executor."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from test_exports import parse_page

from flipviz.bench import BenchConfig, plan, run_bench
from flipviz.bench.config import parse_configs, parse_methods
from flipviz.bench.paper_numbers import METHOD_ORDER, TABLE2, TABLE3
from flipviz.bench.runner import RunSpec, resolve_scene
from flipviz.bench.tables import render_markdown
from flipviz.data.dataset import DatasetError
from flipviz.training.config import EngineConfig, TrainConfig

pytestmark = pytest.mark.bench

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
TINY = [
    "--methods",
    "bl,flip+u",
    "--configs",
    "1,2",
    "--res",
    "24",
    "--steps",
    "30",
    "--batch-rays",
    "256",
    "--mirror-plane",
    "official",
    "--grid-res",
    "16",
    "24",
    "--n-samples",
    "32",
    "--cpus-per-run",
    "1",
    "--workers",
    "2",
]


@pytest.fixture(scope="module")
def cache(render_cache: Path) -> Path:
    return render_cache  # (conftest: the session's)


def _broken_scene(root: Path) -> None:
    """A Blender folder whose orbit lacks the protocol's views: its runs must fail, not the bench."""
    (root / "broken").mkdir(parents=True)
    frame = {"file_path": "./test/r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}
    (root / "broken" / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": [frame]}))


def _results(out: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in (out / "runs").glob("*/result.json")}


def _check_outputs(out: Path, n_runs: int) -> list[dict]:
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == n_runs
    data = json.loads((out / "results.json").read_text())
    assert len(data["runs"]) == n_runs and data["bench"]["steps"] == 30
    table = (out / "table.md").read_text()
    headline = table.split("## Table III")[1].split("\n## ")[0]  # the object's scores stand beside PSNR
    assert "| Scene | Method | PSNR | silhouette IoU | PSNR in the object | depth error | SSIM | LPIPS |" in headline
    assert (
        "| chair | B/L | " in headline and "| chair | Flip+U | " in headline and "| chair | white image | " in headline
    )

    chart = plt.imread(str(out / "psnr_chart.png"))
    assert chart.ndim == 3 and chart.shape[0] > 100
    grid = plt.imread(str(out / "grid_chair.png"))
    assert grid.ndim == 3 and grid.shape[0] > 100
    assert "gain Flip+U - B/L" in table and "gain in the object" in table and "tests within 30 deg" in table
    gain = plt.imread(str(out / "gain_vs_coverage.png"))
    assert gain.ndim == 3 and gain.shape[0] > 100
    tags = parse_page(out / "report.html")  # the same, as one offline page: tables, charts, grid
    assert [t for t, _ in tags].count("table") >= 3 and len([a for t, a in tags if t == "img"]) == 3
    return rows


def _wait_for(cond, p: subprocess.Popen, what: str, timeout: float = 180.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        got = cond()
        if got:
            return got
        assert p.poll() is None, f"the bench ended before {what}:\n" + p.stdout.read().decode()
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_bench_resumes_after_kill_and_records_failures(tmp_path: Path, cache: Path) -> None:
    out = tmp_path / "bench"
    _broken_scene(tmp_path / "data")
    env = dict(os.environ, FLIPVIZ_CACHE=str(cache), PYTHONPATH=str(ROOT))
    cmd = [
        sys.executable,
        "-m",
        "flipviz.bench",
        "--scenes",
        "chair,broken",
        "--data-root",
        str(tmp_path / "data"),
        "--out",
        str(out),
        *TINY,
    ]
    p = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    try:
        # A worker process dies under a run (as if out of memory): the run is failed, the bench goes on.
        started = _wait_for(lambda: sorted((out / "runs").glob("*/started.json")), p, "a run started")[0]
        victim = started.parent.name
        os.kill(json.loads(started.read_text())["pid"], signal.SIGKILL)
        # Then the whole bench is killed as soon as one run has finished.
        _wait_for(lambda: any(r["status"] == "ok" for r in _results(out).values()), p, "a run finished")
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    first = _results(out)
    assert first[victim]["status"] == "failed" and "died" in first[victim]["error"], first[victim]
    done = {k: v for k, v in first.items() if v["status"] == "ok"}
    assert 1 <= len(done) < 4
    mtimes = {k: (out / "runs" / k / "result.json").stat().st_mtime_ns for k in done}

    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    log = r.stdout + r.stderr
    final = _results(out)
    for key, res in done.items():  # finished runs were skipped, not redone
        assert f"skipped {key}" in log
        assert final[key]["run_id"] == res["run_id"]
        assert (out / "runs" / key / "result.json").stat().st_mtime_ns == mtimes[key]
    assert f"{len(done)} skipped" in log
    assert final[victim]["status"] == "ok" and final[victim]["run_id"] != first[victim]["run_id"]  # retried
    assert len(final) == 8
    status = {k: v["status"] for k, v in final.items()}
    assert sorted(status.values()) == ["failed"] * 4 + ["ok"] * 4, status
    for v in final.values():
        if v["scene"] == "broken":  # a one-line error, the rest of the bench went on
            assert v["error"] and "\n" not in v["error"]
        else:
            assert 0 < v["ssim"] <= 1 and v["steps"] == 30
            assert v["versions"]["torch"] and v["versions"]["numpy"] and v["versions"]["flipviz"]
            renders = out / "runs" / v["key"] / "test_renders"
            assert len(list(renders.glob("*_gt.png"))) == 8
            # the reported PSNR is the mean PSNR of the saved renders against their ground truth
            per_view = [v_["name"] for v_ in v["per_view"]]
            again = [_png_psnr(renders / f"{n}.png", renders / f"{n}_gt.png") for n in per_view]
            assert v["psnr"] == pytest.approx(float(np.mean(again)), abs=0.1)
            assert [x["psnr"] for x in v["per_view"]] == pytest.approx(again, abs=0.1)
    rows = _check_outputs(out, 8)
    assert {r["status"] for r in rows if r["scene"] == "broken"} == {"failed"}
    assert "## Failed runs" in (out / "table.md").read_text()
    # The reports can be rebuilt from the run folders alone, without training.
    for f in (
        "results.csv",
        "results.json",
        "table.md",
        "psnr_chart.png",
        "grid_chair.png",
        "report.html",
        "gain_vs_coverage.png",
    ):
        (out / f).unlink()
    run_bench(BenchConfig(methods="bl,flip+u", configs="1,2", steps=30, out=out, report_only=True))
    _check_outputs(out, 8)
    assert _results(out) == final


def _png_psnr(pred: Path, gt: Path) -> float:
    a, b = (plt.imread(str(p))[..., :3].astype(np.float64) for p in (pred, gt))
    return float(-10.0 * np.log10(np.mean((a - b) ** 2)))


def test_bench_runs_use_the_train_defaults():
    """A bench run is `flipviz train` with its defaults, except what the bench sets on purpose."""
    spec = plan(BenchConfig(scenes="chair", methods="flip+u", configs="3"))[0]
    got, want = (
        spec.train_config(BenchConfig()).to_dict(),
        TrainConfig.from_settings(method="flip+u", config=3).to_dict(),
    )
    differ = {k for k in want if got[k] != want[k]}
    assert differ == {"no_rrd", "images_every"}, differ
    assert got["n_samples"] == EngineConfig.n_samples == 64
    train = TrainConfig().settings()
    shared = {f.name for f in fields(BenchConfig)} & set(train) - {"out"}
    assert {k: getattr(BenchConfig(), k) for k in shared} == {k: train[k] for k in shared}


def test_flip_runs_of_a_configuration_share_one_estimated_plane(tmp_path: Path, cache: Path) -> None:
    """--mirror-plane auto (the default): Flip estimates the plane, Flip+U reads it (the same, no second fit)."""
    cfg = BenchConfig(
        scenes="chair",
        methods="flip,flip+u",
        configs="1",
        res=24,
        steps=20,
        batch_rays=256,
        grid_res=(16,),
        n_samples=32,
        out=tmp_path / "b",
        cpus_per_run=1,
        quiet=True,
    )
    res = _results(run_bench(cfg))
    assert sorted(v["status"] for v in res.values()) == ["ok", "ok"], res
    (shared,) = (tmp_path / "b" / "planes").glob("chair-c1-*.json")
    planes = [json.loads((tmp_path / "b" / "runs" / k / "plane.json").read_text()) for k in res]
    assert planes[0] == planes[1] == json.loads(shared.read_text())  # the estimate's own timing too: read, not redone


def test_a_flip_run_that_drops_its_mirrors_takes_its_b_l_twins_result(tmp_path: Path, cache: Path) -> None:
    """With an unconfident plane (the chair's inputs at 24 px), Flip and Flip+U train B/L exactly; the
    bench takes B/L's finished result instead of training it twice: the same scores (checked against
    a Flip run that does train), the run's own plane report, and the test renders."""
    kw = dict(
        scenes="chair",
        configs="1",
        res=24,
        steps=20,
        batch_rays=256,
        grid_res=(16,),
        n_samples=32,
        workers=1,
        cpus_per_run=1,
        quiet=True,
        unconfident_plane="drop",
    )
    res = _results(run_bench(BenchConfig(methods="bl,flip,flip+u", out=tmp_path / "b", **kw)))
    by = {v["method"]: v for v in res.values()}
    assert all(v["status"] == "ok" for v in res.values()), res
    bl = by["bl"]
    for m in ("flip", "flip+u"):
        r = by[m]
        metrics = json.loads((tmp_path / "b" / "runs" / r["key"] / "metrics.json").read_text())
        assert metrics["plane"]["trained"] is False and metrics["plane"]["confidence"] < 0.25  # dropped
        assert r["reused_from"] == bl["key"] and r["psnr"] == bl["psnr"] and r["ssim"] == bl["ssim"]
        assert metrics["method"] == m and metrics["reused_from"] == bl["key"]
        renders = sorted(p.name for p in (tmp_path / "b" / "runs" / r["key"] / "test_renders").glob("*.png"))
        assert len(renders) == 16
    rows = {r["method"]: r for r in csv.DictReader((tmp_path / "b" / "results.csv").open())}
    assert rows["flip"]["reused_from"] == rows["flip+u"]["reused_from"] == bl["key"] and rows["bl"]["reused_from"] == ""
    # the claim behind the reuse: the Flip run, trained, gives B/L's scores to the last digit (it reads the
    # first bench's estimate: the same plane, without a second 10 s fit)
    shutil.copytree(tmp_path / "b" / "planes", tmp_path / "alone" / "planes")
    (trained,) = _results(run_bench(BenchConfig(methods="flip", out=tmp_path / "alone", **kw))).values()
    assert "reused_from" not in trained and trained["psnr"] == bl["psnr"] and trained["ssim"] == bl["ssim"]
    # a Flip run that keeps its mirrors never takes a twin's result
    from flipviz.bench.task import RunTask, _finished_twin
    from flipviz.training.run import make_trainer

    spec = plan(BenchConfig(methods="flip", **kw))[0]
    keeps = make_trainer(
        spec.train_config(BenchConfig(methods="flip", mirror_plane="official", **kw), tmp_path / "keeps")
    )
    keeps.close()
    assert keeps.spec.mirrors
    assert (
        _finished_twin(
            RunTask("k", str(tmp_path / "keeps"), {}, {}, twin=str(tmp_path / "b" / "runs" / bl["key"])), keeps
        )
        is None
    )


def test_bench_on_ray(tmp_path: Path, cache: Path) -> None:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        cfg = BenchConfig(
            scenes="chair",
            methods="bl,flip+u",
            configs="1",
            res=24,
            steps=30,
            batch_rays=256,
            grid_res=(16, 24),
            n_samples=32,
            out=tmp_path / "ray",
            executor="ray",
        )
        out = run_bench(cfg)
    finally:
        ray.shutdown()
    res = _results(out)
    assert len(res) == 2 and all(v["status"] == "ok" for v in res.values()), res
    assert {v["method"] for v in res.values()} == {"bl", "flip+u"}
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == 2 and all(float(r["psnr"]) > 0 for r in rows)
    assert (out / "grid_chair.png").is_file() and (out / "psnr_chart.png").is_file()


# ------------------------------------------------------------------------- no training


def test_the_table3_study_finds_its_finished_runs_again() -> None:
    """The study resumes across sessions because the bench skips a finished run by its key: the study's
    plan, parsed with today's code, must give every committed run its folder's key. A default changed
    since (--after-drop) or a setting added (--mirror-disagreement-limit) re-ran 3-hour runs."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("study_table3", Path(__file__).parents[1] / "studies/study_table3.py")
    study = importlib.util.module_from_spec(spec)
    sys.modules["study_table3"] = study  # (its dataclasses look their module up)
    spec.loader.exec_module(study)
    from flipviz import cli

    found = 0
    for item in study.PLAN:
        cfg = cli.parse_command(["bench", *item.bench_args(Path("unused"))])
        for res in sorted((study.OUT / item.name / "runs").glob("*/result.json")):
            r = json.loads(res.read_text())
            run = RunSpec(r["scene"], r["data"] or None, r["method"], r["config"])  # the data folder as it ran
            assert run.key(cfg) == res.parent.name, f"{item.name}: {res.parent.name} would run again"
            found += 1
    assert found >= 20  # lego's committed runs (docs/results/table3)


def test_plan_keys_and_ablation(tmp_path: Path) -> None:
    cfg = BenchConfig(scenes="chair,mug", methods="all", configs="1-8", steps=100, res=32)
    specs = plan(cfg)
    assert len(specs) == 2 * 8 * 5
    keys = {s.key(cfg) for s in specs}
    assert len(keys) == len(specs)
    # Table II adds Flip without BA and Flip+U without BA; (BA, no U) is Flip, (BA, U) is Flip+U.
    abl = plan(BenchConfig(scenes="chair", methods="all", configs="1-8", ablation=True))
    assert len(abl) == 8 * 7
    assert {(s.method, s.ba) for s in abl if s.method.startswith("flip")} == {
        ("flip", True),
        ("flip", False),
        ("flip+u", True),
        ("flip+u", False),
    }
    # Keys cover everything that changes the result (steps, res, seed, data path) ...
    s = specs[0]
    changes = (
        dict(steps=101),
        dict(res=33),
        dict(seed=1),
        dict(batch_rays=128),
        dict(field="nerf"),
        dict(grid_res=(8,)),
    )
    for change in changes:
        other = BenchConfig(**{**cfg.__dict__, **change})
        assert s.key(other) != s.key(cfg), change
    # ... and nothing that does not (output folder, workers, executor).
    same = BenchConfig(**{**cfg.__dict__, "out": tmp_path, "workers": 2, "executor": "ray"})
    assert s.key(same) == s.key(cfg)
    # B/L starts first (a Flip run that drops its mirrors takes its result), Flip+U last (the Flip runs
    # of a configuration share one estimated plane: one file per configuration).
    assert [x.method for x in specs[:5]] == ["bl", "bl+u", "flip", "upper", "flip+u"]
    files = {
        (x.scene, x.config, x.method): x.train_config(cfg, tmp_path / x.key(cfg), tmp_path / "planes").flip.plane_file
        for x in specs
    }
    assert (
        files[("chair", 1, "flip")]
        == files[("chair", 1, "flip+u")]
        != files[("chair", 2, "flip")]
        != files[("mug", 2, "flip")]
    )
    assert files[("chair", 1, "bl")] is None and files[("chair", 1, "flip")].parent == tmp_path / "planes"
    official = BenchConfig(**{**cfg.__dict__, "mirror_plane": "official"})
    assert specs[0].train_config(official, tmp_path, tmp_path / "planes").flip.plane_file is None


def test_parsing_and_scene_errors(tmp_path: Path) -> None:
    assert parse_configs("1-8") == list(range(1, 9)) and parse_configs("1,3-4") == [1, 3, 4]
    assert parse_methods("all") == list(METHOD_ORDER) and parse_methods("flip+u,bl") == ["flip+u", "bl"]
    for bad in ("0-3", "9", "a"):
        with pytest.raises(ValueError):
            parse_configs(bad)
    with pytest.raises(ValueError, match="unknown method"):
        parse_methods("flip,nope")
    assert resolve_scene("chair", None) == ("chair", None)
    with pytest.raises(DatasetError, match="--data-root"):
        resolve_scene("lego", None)
    with pytest.raises(DatasetError, match="transforms_test.json"):
        resolve_scene("lego", tmp_path)
    _broken_scene(tmp_path)
    assert resolve_scene("broken", tmp_path) == ("broken", str((tmp_path / "broken").resolve()))


def test_table_shows_paper_numbers_for_nerf_synthetic_scenes() -> None:
    def row(scene, data, method, config, psnr):
        return {
            "key": f"{scene}{method}{config}",
            "scene": scene,
            "data": data,
            "method": method,
            "config": config,
            "ba": method.startswith("flip"),
            "uncertainty": method.endswith("+u"),
            "default_flags": True,
            "status": "ok",
            "psnr": psnr,
            "ssim": 0.5,
            "lpips": "unavailable",
            "train_seconds": 10.0,
        }

    rows = [
        row("lego", "/d/lego", "bl", 1, 10.0),
        row("lego", "/d/lego", "bl", 2, 12.0),
        row("lego", "/d/lego", "flip+u", 1, 15.0),
        row("chair", "", "bl", 1, 20.0),
    ]
    md = render_markdown(rows, BenchConfig(scenes="lego,chair", methods="bl,flip+u", configs="1,2"))
    line = lambda start: next(ln for ln in md.splitlines() if ln.startswith(start))  # noqa: E731
    assert line("| lego | B/L | ").startswith(
        "| lego | B/L | 11.00 (11.57) |"
    )  # mean of configurations, paper beside it
    assert line("| lego | Flip+U").startswith("| lego | Flip+U †1/2 | 15.00 (17.79) |")  # one of two configurations
    assert "(" not in line("| chair | B/L")  # built-in chair: no paper numbers
    assert line("| **Mean** | B/L | ").startswith("| **Mean** | B/L | 15.50 |")  # over scenes: (11 + 20) / 2


def test_per_config_table_reports_the_flip_runs_coverage_and_plane() -> None:
    """With auto, B/L's would-be mirrors use another plane: the coverage shown is Flip+U's, beside
    its plane's confidence, whether its mirrors were dropped, and its error before -> after training."""
    from flipviz.bench.tables import per_config_table

    def row(method: str, config: int, psnr: float, angle: float, plane: dict | None) -> dict:
        m = {"coverage": {"mean_angle_deg": angle, "within_30": 1.0 if angle < 30 else 0.0}} | (
            {"plane": plane} if plane else {}
        )
        return {
            "scene": "mug",
            "method": method,
            "config": config,
            "default_flags": True,
            "status": "ok",
            "psnr": psnr,
            "metrics": m,
        }

    refined = {
        "confidence": 0.3,
        "trained": True,
        "error_deg": 1.25,
        "error_offset": 0.04,
        "refined_error_deg": 0.1,
        "refined_error_offset": 0.002,
        "kept_mirrors": 5,  # per-mirror verdicts (config 1's run predates them: "-")
        "n_mirrors": 8,
    }
    rows = [
        row("bl", 1, 20.0, 1.0, None),
        row("flip+u", 1, 20.0, 45.0, {"confidence": 0.1, "trained": False}),
        row("bl", 2, 20.0, 1.0, None),
        row("flip+u", 2, 21.5, 2.0, refined),
    ]
    lines = per_config_table(rows, ["bl", "flip+u"]).splitlines()
    assert lines[2].endswith("| +0.00 | - | 45.0 | 0% | 0.100 (dropped) | - | - |"), lines[2]
    assert lines[3].endswith("| +1.50 | - | 2.0 | 100% | 0.300 | 1.25° / 0.040 -> 0.10° / 0.002 | 5 of 8 |"), lines[3]


def test_paper_numbers_match_protocol_and_tex() -> None:
    protocol, tex = SHARED / "PROTOCOL.md", SHARED / "paper" / "just_flip.tex"
    if not protocol.is_file() or not tex.is_file():
        pytest.skip("../shared (protocol and paper) not present in this checkout")
    names = {
        "Chairs": "Chairs",
        "Lego": "Lego",
        "Materials": "Materials",
        "Ship": "Ship",
        "Drum": "Drum",
        "Ficus": "Ficus",
        "Hotdog": "Hotdog",
        "Mic": "Mic",
        "Mean": "Mean",
    }
    n = 0
    for line in protocol.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells and cells[0] in names and len(cells) == 6:
            assert [TABLE3["psnr"][cells[0]][m] for m in METHOD_ORDER] == [float(c) for c in cells[1:]]
            n += 1
    assert n == 9
    n = 0
    for line in tex.read_text().splitlines():
        line = re.sub(r"\\textbf\{([^}]*)\}", r"\1", line.split("\\\\")[0])  # drop bold and the row end
        cells = [c.strip() for c in line.split("&")]
        if len(cells) == 16 and cells[0] in names:
            vals = [float(c) for c in cells[1:]]
            for k, metric in enumerate(("psnr", "ssim", "lpips")):
                assert [TABLE3[metric][cells[0]][m] for m in METHOD_ORDER] == vals[5 * k : 5 * k + 5]
            n += 1
        if len(cells) == 5 and cells[0] in ("-", "\\checkmark") and cells[1] in ("-", "\\checkmark"):
            key = (cells[0] == "\\checkmark", cells[1] == "\\checkmark")
            assert [TABLE2[key][m] for m in ("psnr", "ssim", "lpips")] == [float(c) for c in cells[2:]]
            n += 1
    assert n == 9 + 4


def test_ablation_table_rows() -> None:
    def row(method, ba, u, config, psnr):
        return {
            "key": f"{method}{ba}{config}",
            "scene": "mug",
            "data": "",
            "method": method,
            "config": config,
            "ba": ba,
            "uncertainty": u,
            "default_flags": ba,
            "status": "ok",
            "psnr": psnr,
            "ssim": 0.5,
            "lpips": 0.2,
            "train_seconds": 1.0,
        }

    rows = [
        row("flip", False, False, 1, 10.0),
        row("flip", True, False, 1, 11.0),
        row("flip+u", False, True, 1, 12.0),
        row("flip+u", True, True, 1, 13.0),
        row("flip+u", True, True, 2, 15.0),
        {**row("flip", False, False, 2, 99.0), "status": "failed"},
    ]
    md = render_markdown(rows, BenchConfig(scenes="mug", methods="flip,flip+u", configs="1,2", ablation=True))
    table2 = md.split("## Table II:")[1].split("##")[0]
    lines = [ln for ln in table2.splitlines() if ln.startswith("| ") and ("✓" in ln or "| - | - |" in ln)]
    assert [ln.split(" | ")[:3] for ln in lines] == [
        ["| -", "-", "10.00"],
        ["| ✓", "-", "11.00"],
        ["| -", "✓", "12.00"],
        ["| ✓", "✓", "14.00"],
    ]
    assert "16.636" in lines[0] and "17.620" in lines[3]  # the paper's Table II beside ours


def test_a_resumed_runs_wall_time_counts_its_earlier_attempts(tmp_path: Path) -> None:
    """A run stopped (or killed) and resumed from its checkpoint reports the wall time of every attempt up to
    that checkpoint, not only the last attempt's (the NeRF Flip+U had shown 5148 s for 10 918 s of training)."""
    from flipviz.bench.results import STARTED_FILE
    from flipviz.bench.task import RunTask, earlier_wall_seconds, execute_run
    from flipviz.training.config import TrainConfig
    from flipviz.training.events import Observer
    from flipviz.training.run import make_trainer

    run_dir = tmp_path / "run"
    cfg = TrainConfig.from_settings(
        scene="chair", method="bl", res=16, steps=20, batch_rays=64, grid_res=(16,), no_rrd=True, out=run_dir
    )
    (run_dir / STARTED_FILE).parent.mkdir(parents=True)
    (run_dir / STARTED_FILE).write_text(json.dumps({"started": time.time() - 100.0}))
    assert earlier_wall_seconds(run_dir) == 0.0  # an attempt that left no checkpoint owes nothing

    trainer = make_trainer(cfg)

    class StopAt10(Observer):
        def on_step(self, e) -> None:
            if e.step >= 10:
                trainer.stop()

    trainer.add_observer(StopAt10())
    trainer.run()  # stopped at step 10, its checkpoint written
    now = time.time()
    (run_dir / STARTED_FILE).write_text(json.dumps({"started": now - 100.0, "earlier_wall_seconds": 50.0}))
    os.utime(run_dir / "checkpoint.pt", (now - 40.0, now - 40.0))  # the last attempt: 60 s to its checkpoint
    assert earlier_wall_seconds(run_dir) == pytest.approx(110.0, abs=1.0)
    result = execute_run(RunTask("k", str(run_dir), cfg.to_dict(), {"scene": "chair", "method": "bl"}, progress=False))
    assert result["status"] == "ok" and result["resumed_from_step"] == 10, result
    assert result["earlier_wall_seconds"] == pytest.approx(110.0, abs=1.0)
    assert result["wall_seconds"] >= 110.0 + (result["finished"] - result["started"]) - 1e-6
