"""TrainConfig by concern: four groups in code, one flat flag per setting on the command line, flat
settings in every saved run."""

from __future__ import annotations

import ast
import contextlib
import io
import re
from dataclasses import fields
from pathlib import Path

import pytest

from flipviz.cli import parse_command
from flipviz.training.config import GROUPS, SETTINGS, TrainConfig
from flipviz.training.saved_run import run_config

ROOT = Path(__file__).resolve().parents[1]
# the flat settings every run saved before the split (checkpoint.pt's "config", metrics.json's "settings")
SAVED_BEFORE = """scene data inputs method config res steps batch_rays field mirror_plane mirror_pose plane_file
estimate_after join_lr unconfident_plane disagreement_limit after_drop refine_plane plane_lr plane_start ba
ba_start uncertainty refine background density_on nll_channels beta_from seed device out log_every
images_every rrd no_rrd rerun_serve resume overwrite uncertainty_start density_weight checkpoint_every
eval_on_stop beta2_mode n_samples grid_res preset""".split()
ADDED = [
    "eval_views",
    "eval_tune_steps",
    "eval_every",
    "lr_end",
    "entropy_weight",
    "plane_ramp",
]  # since: read back at their defaults
LATER = ["mirror_disagreement_limit"]  # since: read back as what runs saved before it did (no per-mirror verdict)


def test_each_flat_flag_lands_in_its_group():
    cfg = parse_command(
        ["train", "--scene", "mug", "--data", "some/folder", "--config", "4", "--steps", "7", "--field", "nerf"]
        + ["--plane-lr", "0.5", "--no-ba", "--mirror-pose", "lookat", "--log-every", "3", "--no-rrd", "--method", "bl"]
    )
    assert (cfg.data.scene, cfg.data.path, cfg.data.config) == ("mug", Path("some/folder"), 4)
    assert (cfg.engine.steps, cfg.engine.field) == (7, "nerf")
    assert (cfg.flip.plane_lr, cfg.flip.ba, cfg.flip.mirror_pose) == (0.5, False, "lookat")
    assert (cfg.output.log_every, cfg.output.no_rrd, cfg.method) == (3, True, "bl")


def test_the_help_lists_the_settings_by_concern():
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        parse_command(["train", "--help"])
    text = out.getvalue()
    heads = [text.index(f"{g} options") for g in GROUPS]
    assert heads == sorted(heads)  # data, engine, flip, output: in that order
    flag = lambda name: re.search(rf"^\W*--{name}\b", text, re.M).start()  # noqa: E731 (the line it starts)
    assert heads[0] < flag("scene") < heads[1] < flag("steps") < heads[2] < flag("plane-lr") < heads[3] < flag("rrd")


def test_settings_are_saved_flat_by_their_flag_names_and_read_back_whole():
    cfg = TrainConfig.from_settings(
        scene="mug", data=Path("x/y"), steps=9, plane_lr=0.25, ba_start=0.5, grid_res=(16, 32), out=Path("o")
    )
    saved = cfg.to_dict()
    assert sorted(saved) == sorted(SAVED_BEFORE + ADDED + LATER)  # the keys every run saved before the split, and since
    assert (saved["data"], saved["steps"], saved["plane_lr"], saved["out"]) == ("x/y", 9, 0.25, "o")
    assert run_config(saved) == cfg
    assert len(SETTINGS) + 2 == len(SAVED_BEFORE + ADDED + LATER)  # no name in two groups (method, preset: top-level)
    before = run_config({k: v for k, v in saved.items() if k not in ADDED + LATER})  # a run saved before them
    assert before == cfg.with_settings(mirror_disagreement_limit=float("inf"))


def test_with_settings_changes_only_what_it_names_and_refuses_what_no_group_has():
    cfg = TrainConfig()
    changed = cfg.with_settings(steps=5, scene="lamp", method="bl")
    assert (changed.engine.steps, changed.data.scene, changed.method) == (5, "lamp", "bl")
    assert (changed.flip, changed.output) == (cfg.flip, cfg.output) and cfg.engine.steps == 600  # a copy
    changed.output.out = Path("elsewhere")  # a group set on the copy (as `flipviz train` sets its folder)
    assert cfg.output.out is None  # is not the original's: no group is shared between the two
    with pytest.raises(TypeError, match="stepz"):
        cfg.with_settings(stepz=5)
    with pytest.raises(TypeError, match="engine"):  # a group is not a setting
        cfg.with_settings(engine=cfg.engine)


def test_the_flip_module_reads_only_what_just_flip_adds():
    """training/flip.py takes the `flip` group (and the step count), never the whole run's settings."""
    tree = ast.parse((ROOT / "flipviz/training/flip.py").read_text())
    imports = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "flipviz.training.config"]
    names = {a.name for n in imports for a in n.names}
    assert names == {"FlipConfig"}
    assert {f.name for f in fields(GROUPS["flip"])} >= {"mirror_plane", "plane_lr", "disagreement_limit", "uncertainty"}
