"""Safe to open: a run folder someone hands you never runs code, and a browser never names a folder
the command line did not (docs/RELIABILITY.md, "Security")."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from flipviz import cli
from flipviz.errors import UserError
from flipviz.files import inside_roots
from flipviz.training.checkpoint import load_checkpoint
from flipviz.training.config import TrainConfig
from flipviz.training.saved_run import open_run
from flipviz.training.trainer import Trainer

TINY = dict(
    scene="chair", res=24, batch_rays=256, n_samples=32, grid_res=(24,), images_every=0, mirror_plane="official"
)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A real finished Flip+U run (its checkpoint has poses and both optimisers)."""
    out = tmp_path_factory.mktemp("real") / "run"
    Trainer(TrainConfig.from_settings(**TINY, steps=3, method="flip+u", out=out)).run()
    return out


class Payload:
    """What a crafted pickle holds: unpickling it calls os.mkdir(marker), i.e. runs code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (str(self.marker),))


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_a_pickle_payload_in_a_checkpoint_never_runs(run_folder, tmp_path, capsys):
    marker = tmp_path / "pwned"
    state = torch.load(run_folder / "checkpoint.pt", weights_only=True)
    state["config"]["note"] = Payload(marker)  # the rest is a real checkpoint
    shared = tmp_path / "shared_run"
    shared.mkdir()
    torch.save(state, shared / "checkpoint.pt")
    for open_it in (lambda: load_checkpoint(shared), lambda: open_run(shared)):  # resume, report, video, Compare's B
        with pytest.raises(UserError, match="never loads those"):
            open_it()
    for args in (
        ["video", str(shared)],
        ["report", str(shared)],
        ["train", "--scene", "chair", "--res", "24", "--mirror-plane", "official", "--resume", str(shared)],
    ):
        assert cli.main(args) == 2
        assert "never loads those" in one_line(capsys)
    assert not marker.exists()


@pytest.mark.parametrize(
    "damage, says",
    [
        (lambda s: s.pop("opt_field"), "missing 'opt_field'"),
        (lambda s: s["opt_field"]["param_groups"].append(dict(s["opt_field"]["param_groups"][0])), "does not fit"),
        (lambda s: s["poses"].update(stray=torch.zeros(3)), "does not fit"),
        (lambda s: s.update(rng=torch.zeros(3, dtype=torch.uint8)), "does not fit"),
        (lambda s: s.update(step="ten"), "not a whole number"),
        (lambda s: s.update(step=2.5), "not a whole number"),
        (lambda s: s.update(config=["a", "list"]), "not a flipviz checkpoint"),
    ],
    ids=["no-opt-field", "extra-param-group", "stray-pose-key", "bad-rng", "step-text", "step-float", "config-list"],
)
def test_a_crafted_checkpoint_is_one_line_on_resume(run_folder, tmp_path, capsys, damage, says):
    state = torch.load(run_folder / "checkpoint.pt", weights_only=True)
    damage(state)
    bad = tmp_path / "bad.pt"
    torch.save(state, bad)
    args = [
        "train",
        *sum(([f"--{k.replace('_', '-')}", str(v)] for k, v in TINY.items() if k != "grid_res"), []),
        "--grid-res",
        "24",
        "--method",
        "flip+u",
        "--steps",
        "5",
        "--resume",
        str(bad),
        "--out",
        str(tmp_path / "new"),
    ]
    assert cli.main(args) == 2
    assert says in one_line(capsys)


def test_browser_named_folders_stay_inside_the_roots(tmp_path):
    root, outside = tmp_path / "runs", tmp_path / "private"
    (root / "a").mkdir(parents=True)
    outside.mkdir()
    (root / "link").symlink_to(outside)
    assert inside_roots(root / "a", [root], "run folder") == (root / "a").resolve()
    assert inside_roots(str(root), [root], "run folder") == root.resolve()
    for bad in (outside, root / ".." / "private", root / "link", "/etc", "~/.ssh"):
        with pytest.raises(UserError, match="outside the folders this app may open") as e:
            inside_roots(bad, [root], "run folder")
        assert "\n" not in str(e.value)
    with pytest.raises(UserError, match="outside"):
        inside_roots(root / "a", [], "run folder")  # no root named: nothing is open


def test_run_b_never_reads_a_dataset_outside_the_roots_nor_says_whether_it_exists(run_folder, tmp_path):
    """Issue 44: a run folder under a browse root whose saved settings name a dataset elsewhere (any path:
    /etc, or one that does not exist) is refused by the same line, which never says whether that path exists;
    one inside the roots that is missing says so. Without `roots` (the CLI's own report and video) the
    dataset is the user's to name."""
    root = tmp_path / "runs"
    state = torch.load(run_folder / "checkpoint.pt", weights_only=True)
    said = {}
    for name, data in [("etc", "/etc"), ("nowhere", "/nonexistent/lego"), ("inside", str(root / "gone"))]:
        run = root / name
        run.mkdir(parents=True)
        torch.save(state | {"config": state["config"] | {"data": data, "plane_file": "/etc"}}, run / "checkpoint.pt")
        with pytest.raises(UserError) as e:
            open_run(run, roots=[root])
        said[name] = str(e.value).replace(data, "PATH").replace(name, "RUN")
    assert said["etc"] == said["nowhere"] and "outside the folders this app may open" in said["etc"]
    assert "not found" in said["inside"]
    with pytest.raises(UserError, match="not found from here"):  # the CLI (no roots): the user named the run
        open_run(root / "nowhere")


def test_the_reports_refined_plane_reads_only_a_plane():
    """`flipviz report` draws the plane from metrics.json: anything but three finite numbers for its point
    and a non-zero normal is no plane (a crafted file gets the starting plane, not a traceback)."""
    from flipviz.viz.export.report import refined_plane

    good = {"plane": {"refined": {"point": [0, 0, 0], "normal": [1, 0, 0]}}}
    assert refined_plane(good) is not None
    for bad in ({}, {"plane": 3}, {"plane": {"refined": "x"}}, {"plane": {"refined": {"point": ["a"] * 3}}}):
        assert refined_plane(bad) is None
    for point, normal in (([0, 0], [1, 0, 0]), ([0, 0, float("nan")], [1, 0, 0]), ([0, 0, 0], [0, 0, 0])):
        assert refined_plane({"plane": {"refined": {"point": point, "normal": normal}}}) is None
