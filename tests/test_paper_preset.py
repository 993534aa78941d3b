"""`--preset paper` (the paper's vanilla NeRF setting) and benchmarks/gpu_paper.sh, checked on the CPU
with a tiny step count (on CUDA where one is present: see the README)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import tyro

from flipviz.model.nerf_field import NerfConfig
from flipviz.training.config import TrainConfig
from flipviz.training.setup import model_config

ROOT = Path(__file__).resolve().parents[1]
LEGO = Path(os.environ.get("FLIPVIZ_LEGO", ROOT.parent / "shared/data/nerf_synthetic/lego"))


def test_the_paper_preset_sets_the_papers_setting_and_yields_to_given_values():
    cfg = tyro.cli(TrainConfig, args=["--preset", "paper", "--method", "flip+u"])
    assert (cfg.field, cfg.n_samples, cfg.steps, cfg.batch_rays) == ("nerf", 128, 50_000, 1024)
    assert int(cfg.uncertainty_start * cfg.steps) == 10_000  # the NLL from 10k of 50k iterations
    mc = model_config(cfg)
    assert isinstance(mc.field, NerfConfig) and (mc.field.depth, mc.field.width) == (8, 256)
    assert mc.field.lr * mc.field.lr_decay == pytest.approx(1e-4) and mc.field.barf_c2f == (0.1, 0.5)
    assert mc.n_samples == 128 and mc.w_entropy == 0.0 and mc.beta_min == 0.1
    mine = tyro.cli(TrainConfig, args=["--preset", "paper", "--steps", "7", "--n-samples", "32"])
    assert (mine.steps, mine.n_samples, mine.field) == (7, 32, "nerf")  # what you pass wins
    fast = TrainConfig()
    assert (fast.field, fast.n_samples, fast.steps) == ("grid", 64, 600) and model_config(fast).w_entropy > 0


@pytest.mark.skipif(not (LEGO / "transforms_test.json").is_file(), reason="needs the NeRF-synthetic lego")
@pytest.mark.skipif(shutil.which("timeout") is None, reason="needs coreutils' timeout")
def test_gpu_paper_script_runs_on_the_cpu_with_a_tiny_step_count(tmp_path):
    env = dict(os.environ, DEVICE="cpu", SECONDS_PER_RUN="240", STEPS="2", BATCH="64", RES="16", LEGO=str(LEGO),
               OUT=str(tmp_path / "out"), PYTHON=str(Path(os.sys.executable)), PYTHONPATH=str(ROOT))  # fmt: skip
    r = subprocess.run(["bash", str(ROOT / "benchmarks/gpu_paper.sh")], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((tmp_path / "out/summary.json").read_text())
    assert summary["preset"] == "paper" and [x["method"] for x in summary["runs"]] == ["bl", "flip+u"]
    for run in summary["runs"]:
        assert run["steps"] == 2 and run["steps_per_s"] > 0 and 0 < run["psnr"] < 60
    settings = json.loads((tmp_path / "out/lego-flip_u/metrics.json").read_text())["settings"]
    assert (settings["field"], settings["n_samples"], settings["preset"]) == ("nerf", 128, "paper")
    assert "PSNR" in r.stdout
