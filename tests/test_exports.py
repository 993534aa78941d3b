"""Comparing and exporting finished runs: camera paths, `flipviz video`, `flipviz compare` (the runs'
Rerun recordings in one), `flipviz report` and the bench's report.html (offline HTML pages)."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from browser import chromium, chromium_available

from flipviz.data.builtin import render_view
from flipviz.data.cameras import azimuth_deg
from flipviz.errors import UserError
from flipviz.files import FolderLock
from flipviz.training import trainer as trainer_module
from flipviz.training.checkpoint import load_checkpoint
from flipviz.training.config import TrainConfig
from flipviz.training.evaluate import image_psnr
from flipviz.training.run import train
from flipviz.training.saved_run import Run, open_run
from flipviz.viz.camera_path import orbit_path, read_keyframes, unobserved_path, write_keyframes
from flipviz.viz.export.report import ReportConfig, write_run_report
from flipviz.viz.export.video import TITLE_H, VideoConfig, make_video, path_cameras
from flipviz.viz.rerun.compare import write_comparison
from flipviz.viz.rerun.observer import make_rerun_observer

pytestmark = pytest.mark.slow

RES = 32


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Two tiny finished chair runs, B/L and Flip+U, with checkpoints and Rerun recordings."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for method in ("bl", "flip+u"):
        cfg = TrainConfig.from_settings(
            scene="chair",
            method=method,
            res=RES,
            steps=60,
            batch_rays=256,
            n_samples=32,
            grid_res=(16, 24),
            mirror_plane="official",
            images_every=30,
            log_every=10,
            out=root / method,
        )
        rec = make_rerun_observer(cfg, cfg.output.out)
        _, metrics = train(cfg, [rec])
        rec.close()
        assert metrics["status"] == "finished"
        out[method] = root / method
    return out


def test_open_run_renders_what_the_run_scored(runs):
    metrics = json.loads((runs["flip+u"] / "metrics.json").read_text())
    lock = FolderLock(runs["flip+u"])  # e.g. the app still serving it: opening to render neither waits nor writes
    t = open_run(runs["flip+u"])
    lock.release()
    assert t.step == 60 and t.cfg.method == "flip+u" and isinstance(t, Run)  # a record: no Trainer is built
    psnrs = [image_psnr(t.render(v.camera, ("rgb",))["rgb"], v.rgb) for v in t.split.tests]
    assert float(np.mean(psnrs)) == pytest.approx(metrics["psnr"], abs=1e-4)
    trained = load_checkpoint(runs["flip+u"])["mirror_c2w"].numpy()  # the refined mirrored poses, as trained
    assert len(t.mirror_cameras()) == len(trained) == 8 and np.array_equal(t.mirror_c2w(), trained)
    assert not np.allclose(trained, np.stack([v.camera.c2w for v in t.mirror_views]), atol=1e-6)  # BA moved them
    with pytest.raises(UserError, match="not a run folder"):
        open_run(runs["flip+u"] / "test_renders")


def test_unobserved_path_lands_on_every_test_view_in_azimuth_order(runs):
    setup = open_run(runs["bl"]).setup_event
    tests = [c.camera for c in setup.cameras if c.kind == "test"]
    path = unobserved_path(setup, 30)
    hits = [next((i for i, c in enumerate(path) if np.allclose(c.c2w, t.c2w, atol=1e-9)), None) for t in tests]
    assert None not in hits and len(set(hits)) == len(tests)
    assert (len(path) - 1) % (len(tests) - 1) == 0 and abs(len(path) - 30) <= len(tests)
    center, up = np.asarray(setup.sphere_center), np.asarray(setup.up)
    az = np.unwrap(np.radians([azimuth_deg(c.center - center, up) for c in path]))
    assert np.all(np.diff(az) > 0) or np.all(np.diff(az) < 0)  # one way across, no jumps back
    radii = [np.linalg.norm(c.center - center) for c in path]
    assert np.ptp(radii) < 1e-6 * np.mean(radii)  # on the ring of the test views
    ring = orbit_path(setup, 24)
    steps = np.degrees(np.diff(np.unwrap(np.radians([azimuth_deg(c.center - center, up) for c in ring]))))
    assert len(ring) == 24 and np.allclose(steps, steps[0]) and abs(steps.sum() + steps[0]) == pytest.approx(360.0)


def test_keyframes_round_trip_and_are_hit(runs, tmp_path):
    setup = open_run(runs["bl"]).setup_event
    keys = [c.camera for c in setup.cameras if c.kind == "test"][:3]
    path = write_keyframes(tmp_path / "keyframes.json", keys)
    back = read_keyframes(path, keys[0].width)
    assert all(np.allclose(a.c2w, b.c2w) and a.focal == pytest.approx(b.focal) for a, b in zip(keys, back))
    cams = path_cameras(setup, str(path), 21, RES)
    assert len(cams) == 21
    for k, i in zip(keys, (0, 10, 20)):
        assert np.allclose(cams[i].c2w, k.c2w, atol=1e-9)
    (tmp_path / "bad.json").write_text('{"keyframes": [{"c2w": [1, 2]}]}')
    with pytest.raises(UserError, match="not a keyframes file"):
        read_keyframes(tmp_path / "bad.json", RES)


def test_video_of_two_runs_decodes_with_its_frames_and_ground_truth(runs, tmp_path):
    cfg = VideoConfig(
        runs=[runs["bl"], runs["flip+u"]],
        path="unobserved",
        frames=15,
        res=48,
        out=tmp_path / "v.mp4",
        gif=tmp_path / "v.gif",
    )
    mp4, gif = make_video(cfg)
    setup = open_run(runs["bl"]).setup_event
    cams = path_cameras(setup, "unobserved", 15, 48)
    reader = imageio.get_reader(mp4)
    frames = [f for f in reader]
    row_h = 2 * TITLE_H + 48
    assert len(frames) == len(cams)
    assert frames[0].shape[:2] == (2 * row_h + (-2 * row_h) % 16, 4 * 48)
    # every frame's ground-truth panel is the scene seen from that frame's camera (ray cast), in both rows
    for i in (0, len(cams) // 2 + 1):
        truth = render_view("chair", cams[i])[0]
        for row in range(2):
            y = row * row_h + 2 * TITLE_H
            panel = frames[i][y : y + 48, 48:96].astype(np.float32) / 255.0
            assert image_psnr(panel, truth) > 25.0
        assert (
            image_psnr(frames[i][2 * TITLE_H : 2 * TITLE_H + 48, :48] / 255.0, truth) < 25.0
        )  # a render, not the truth
    g = imageio.mimread(gif)
    assert len(g) == len(cams)  # under 40 frames: every frame
    with pytest.raises(UserError, match="one run folder, or two"):
        make_video(VideoConfig(runs=[runs["bl"]] * 3))


def test_compare_merges_both_recordings_under_their_names(runs, tmp_path):
    from rerun.chunk import RrdReader

    out, labels = write_comparison([runs["bl"], runs["flip+u"]], tmp_path / "compare.rrd")
    assert labels == ["bl", "flip_u"]
    reader = RrdReader(str(out))
    assert reader.blueprints()  # the side-by-side layout travels in the file
    paths = {c.entity_path for c in reader.stream()}
    for label in labels:
        assert f"/{label}/views/test/r_50/render" in paths
        assert any(p.startswith(f"/{label}/world/cameras/input/") for p in paths)
        assert any(p.startswith(f"/{label}/curves/train/") for p in paths)
    assert any(p.startswith("/flip_u/world/cameras/mirror/") for p in paths)
    assert not any(p.startswith("/bl/world/cameras/mirror/") for p in paths)  # B/L has no mirrors
    assert not any(re.match(r"^/(world|views|curves)/", p) for p in paths)  # nothing left un-prefixed
    with pytest.raises(UserError, match="no Rerun recording"):
        write_comparison([runs["bl"], tmp_path], tmp_path / "x.rrd")


class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs) -> None:
        self.tags.append((tag, dict(attrs)))


def parse_page(path: Path) -> list[tuple[str, dict]]:
    """The page's tags; it must be self-contained: every image embedded, no script, no remote link."""
    p = _Page()
    p.feed(path.read_text())
    assert not [t for t, _ in p.tags if t in ("script", "link", "iframe")]
    for tag, attrs in p.tags:
        for key in ("src", "href"):
            assert not attrs.get(key, "data:").startswith(("http", "//", "file:")), (tag, attrs)
        if tag == "img":
            assert attrs["src"].startswith("data:image/")
    return p.tags


def test_run_report_is_one_offline_page(runs, tmp_path, monkeypatch):
    def no_trainer(*a, **k):
        raise AssertionError("a finished run opens as a saved_run.Run, not a Trainer")

    monkeypatch.setattr(trainer_module.Trainer, "__init__", no_trainer)
    out = write_run_report(ReportConfig(run=runs["flip+u"], out=tmp_path / "report.html", res=RES, gif_frames=8))
    tags = parse_page(out)
    imgs = [a for t, a in tags if t == "img"]
    assert len(imgs) == 1 + 8 + 8 + 1  # cameras, 8 unobserved views, 8 mirrored views, the animation
    assert imgs[-1]["src"].startswith("data:image/gif")
    html = out.read_text()
    assert "Flip+U" in html and "PSNR, unobserved views" in html and "silhouette IoU" in html
    plane = json.loads((runs["flip+u"] / "metrics.json").read_text())["plane"]  # the plane training ended with
    assert f"{plane['refined_error_deg']:.3f} deg, offset {plane['refined_error_offset']:.4f} (refined" in html
    if chromium_available():  # and a real browser shows every image from the file alone
        with chromium() as d:
            d.get(out.resolve().as_uri())
            ok = d.execute_script("return Array.from(document.images).map(i => i.complete && i.naturalWidth > 0)")
            assert len(ok) == len(imgs) and all(ok)
            text = d.find_element("tag name", "body").text  # issue 45 item 4: the page states the refined plane
            assert f"{plane['refined_error_deg']:.3f} deg, offset {plane['refined_error_offset']:.4f} (refined" in text


def test_ctrl_c_during_a_video_leaves_no_file_and_bad_runs_are_one_line(runs, tmp_path, capsys):
    """Ctrl-C while frames render: exit 130, no MP4 and no temporary file; a folder that is not a run,
    three runs, a bad keyframes file: one line each, exit 2."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    out = tmp_path / "v.mp4"
    cmd = [
        sys.executable,
        "-m",
        "flipviz.cli",
        "video",
        str(runs["flip+u"]),
        "--frames",
        "400",
        "--res",
        "64",
        "--out",
        str(out),
    ]
    p = subprocess.Popen(cmd, cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
    seen = ""
    t0 = time.monotonic()
    while "frame/s" not in seen and time.monotonic() - t0 < 120:  # tqdm's rate shows once frames render
        seen += p.stderr.read(1)
    p.send_signal(signal.SIGINT)
    err = seen + p.stderr.read()
    assert p.wait(timeout=60) == 130 and "interrupted" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob(".v.*"))
    bad = [
        (["video", str(tmp_path)], "not a run folder"),
        (["video", str(runs["bl"])] * 1 + [str(runs["bl"]), str(runs["bl"])], "one run folder, or two"),
        (["video", str(runs["bl"]), "--path", str(tmp_path / "missing.json")], "keyframes file not found"),
        (["compare", str(runs["bl"]), str(tmp_path)], "no Rerun recording"),
        (["report", str(tmp_path)], "not a run folder"),
    ]
    from flipviz import cli

    for args, message in bad:  # in this process: the same entry point, without starting Python again
        capsys.readouterr()
        code = cli.main(args)
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and len(err.splitlines()) == 1, (args, err)
