"""The Rerun recording of a real (tiny) training run, read back from the .rrd file."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import urllib.request
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import psutil
import pytest
import rerun as rr
from recorder import Recorder
from rerun.chunk import RrdReader

from flipviz.training.config import TrainConfig
from flipviz.training.trainer import Trainer
from flipviz.viz.rerun.blueprint import entity_name
from flipviz.viz.rerun.observer import camera_paths, has_footer, make_rerun_observer

STEPS, LOG_EVERY, IMAGES_EVERY = 10, 2, 5
REPO = Path(__file__).resolve().parents[1]


def read_rrd(path: Path) -> dict[str, list]:
    """entity path -> its record batches (static and temporal), from the file alone."""
    out: dict[str, list] = defaultdict(list)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a killed recording has no footer: RrdReader warns, then scans
        for chunk in RrdReader(path).stream():
            out[chunk.entity_path].append(chunk.to_record_batch())
    return out


def column(batches: list, name: str) -> list:
    """All rows of one component; each row is the list of its instances."""
    return [v for b in batches if name in b.schema.names for v in b.column(name).to_pylist()]


def first(batches: list, name: str):
    """The first instance of the first row of a component."""
    return column(batches, name)[0][0]


def rows_by_step(batches: list, name: str) -> dict[int, object]:
    return {
        s: v
        for b in batches
        if name in b.schema.names
        for s, v in zip(b.column("step").to_pylist(), b.column(name).to_pylist())
    }


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A real Flip+U run on the built-in chair, recorded to a file and served to a local web viewer."""
    out = tmp_path_factory.mktemp("rerun") / "run"
    cfg = TrainConfig.from_settings(
        scene="chair",
        res=32,
        steps=STEPS,
        log_every=LOG_EVERY,
        images_every=IMAGES_EVERY,
        batch_rays=256,
        out=out,
        checkpoint_every=0,
        rerun_serve=True,
        mirror_plane="official",
    )
    trainer = Trainer(cfg)
    obs = make_rerun_observer(cfg, trainer.run_dir, bake=trainer.point_cloud, splats_every=1)
    keep = Recorder()
    trainer.add_observer(obs)
    trainer.add_observer(keep)
    try:
        trainer.run()
        served = _check_served(obs)
    finally:
        obs.close()
    path = trainer.run_dir / "recording.rrd"
    return {"keep": keep, "rrd": read_rrd(path), "path": path, "served": served}


def _check_served(obs) -> dict:
    """While the viewer runs: its URL, what the page returns, which addresses its server listens on."""
    html = urllib.request.urlopen(obs.viewer_url, timeout=10).read()
    listen = {c.laddr.ip for c in psutil.Process(obs.viewer.process.pid).net_connections("tcp") if c.status == "LISTEN"}
    return {"url": obs.viewer_url, "html": html, "listen": listen}


def test_static_scene_entities(run):
    rrd, setup = run["rrd"], run["keep"].setup
    assert (
        first(rrd["/world"], "ViewCoordinates:xyz")
        == rr.components.ViewCoordinatesBatch(rr.ViewCoordinates.RIGHT_HAND_Z_UP).as_arrow_array().to_pylist()[0]
    )
    for e in (
        "/world/sphere",
        "/world/mirror_plane",
        "/world/mirror_plane/normal",
        "/world/mirror_plane/outline",
        "/world/bbox",
        "/run",
    ):
        assert e in rrd, e
    assert first(rrd["/world/sphere"], "Ellipsoids3D:half_sizes") == pytest.approx([setup.sphere_radius] * 3)
    rub = rr.components.ViewCoordinatesBatch(rr.ViewCoordinates.RUB).as_arrow_array().to_pylist()[0]
    kinds = defaultdict(int)
    for info, path in zip(setup.cameras, camera_paths(setup.cameras)):
        kinds[info.kind] += 1
        b = rrd["/" + path]
        assert first(b, "Transform3D:translation") == pytest.approx(info.camera.center, abs=1e-5)
        assert first(b, "Pinhole:camera_xyz") == rub  # OpenGL cameras: x right, y up, looking along -z
        assert bool(column(b, "EncodedImage:blob")) == (info.image is not None)
    assert kinds["input"] == kinds["test"] == kinds["mirror_init"] == 8
    assert ("/world/true_plane/outline" in rrd) == (setup.true_plane is not None)


def test_mirrored_cameras_and_steps(run):
    rrd, keep = run["rrd"], run["keep"]
    mirrors = [entity_name(c.camera.name) for c in keep.setup.cameras if c.kind == "mirror_init"]
    refined = sorted(p for p in rrd if p.startswith("/world/cameras/mirror/"))
    assert refined == sorted(f"/world/cameras/mirror/{m}" for m in mirrors)
    logged = [e.step for e in keep.steps]
    assert logged == list(range(LOG_EVERY, STEPS + 1, LOG_EVERY))
    assert sorted(rows_by_step(rrd["/curves/train/loss"], "Scalars:scalars")) == logged
    for key in ("psnr", "lr_field", "lr_pose"):
        assert f"/curves/{'lr' if key.startswith('lr') else 'train'}/{key}" in rrd
    last = keep.steps[-1]
    for i, m in enumerate(mirrors):
        poses = rows_by_step(rrd[f"/world/cameras/mirror/{m}"], "Transform3D:translation")
        assert sorted(poses) == [0, *logged]  # the initial pose at step 0, then one per StepEvent
        assert poses[last.step][0] == pytest.approx(last.mirror_c2w[i, :3, 3], abs=1e-5)
    rot = rows_by_step(rrd["/curves/mirror/rot_change_deg"], "Scalars:scalars")
    assert rot[last.step] == pytest.approx(last.mirror_rot_change_deg, abs=1e-6)
    assert "/curves/mirror/rot_err_deg" in rrd and "/curves/test/test_psnr" in rrd


def test_the_refined_plane_moves_in_the_recording(run):
    """--refine-plane (the default): the mirror plane's transform is logged at step 0 and at every StepEvent,
    where the event has it, with its error against the true plane as curves. Its square, outline and normal
    are logged once (static, in the plane's own frame): issue 45, the scene view shows everything up to the
    cursor, and a square logged per step stacked into opaque slabs in the web viewer."""
    rrd, keep = run["rrd"], run["keep"]
    logged = [e.step for e in keep.steps]
    poses = rows_by_step(rrd["/world/mirror_plane"], "Transform3D:mat3x3")
    assert sorted(poses) == [0, *logged]
    last = keep.steps[-1]
    assert last.plane is not None and last.plane_err_deg is not None
    R = np.asarray(poses[last.step][0], dtype=np.float64).reshape(3, 3).T  # (stored column-major)
    assert R[:, 2] == pytest.approx(last.plane.normal, abs=1e-5)  # the frame's z: the refined normal
    where = rows_by_step(rrd["/world/mirror_plane"], "Transform3D:translation")
    assert where[last.step][0] == pytest.approx(last.plane.point, abs=1e-5)
    for part, column in (("", "Mesh3D:vertex_positions"), ("/normal", "Arrows3D:vectors")):
        rows = [b for b in rrd[f"/world/mirror_plane{part}"] if column in b.schema.names]
        assert rows and all("step" not in b.schema.names for b in rows), part  # static: drawn once
    assert rows_by_step(rrd["/curves/plane/err_deg"], "Scalars:scalars")[last.step] == pytest.approx(
        [last.plane_err_deg]
    )
    assert sorted(rows_by_step(rrd["/curves/plane/err_offset"], "Scalars:scalars")) == logged


def test_beta2_frames_equal_the_model_maps(run):
    rrd, keep = run["rrd"], run["keep"]
    assert [e.step for e in keep.images] == [IMAGES_EVERY, STEPS]  # periodic, then the final render
    ranges = set()
    for ev in keep.images:
        for v in ev.mirror_views:
            b = rrd[f"/views/mirror/{entity_name(v.name)}/beta2"]
            buf, fmt, rng = (
                rows_by_step(b, c)[ev.step]
                for c in ("DepthImage:buffer", "DepthImage:format", "DepthImage:depth_range")
            )
            fmt = fmt[0]
            got = np.frombuffer(bytes(buf[0]), dtype=np.float16).reshape(fmt["height"], fmt["width"])
            np.testing.assert_allclose(got.astype(np.float32), v.beta2, rtol=1e-3, atol=1e-7)  # float16 storage
            ranges.add(tuple(rng[0]))
        for v in ev.test_views:
            for part in ("render", "error", "depth", "opacity"):
                batches = rrd[f"/views/test/{entity_name(v.name)}/{part}"]
                assert ev.step in {s for b in batches for s in b.column("step").to_pylist()}, part
            assert f"/views/test/{entity_name(v.name)}/gt" in rrd
    assert len(ranges) == 1  # one fixed colour range for the whole run: frames are comparable


def test_trajectories_grow_linearly(run):
    rrd, keep = run["rrd"], run["keep"]
    m = sum(c.kind == "mirror_init" for c in keep.setup.cameras)
    strips = rows_by_step(rrd["/world/trajectories"], "LineStrips3D:strips")
    steps = sorted(strips)
    assert steps == [e.step for e in keep.steps]
    # Each logged step adds one segment per camera: after k steps the file holds 2 m k points, not O(k^2).
    total = 0
    for k, s in enumerate(steps, start=1):
        assert len(strips[s]) == m and all(len(seg) == 2 for seg in strips[s])
        total += sum(len(seg) for seg in strips[s])
        assert total == 2 * m * k
    # Consecutive segments join up: each starts where the previous one ended.
    for a, b in zip(steps, steps[1:]):
        np.testing.assert_allclose([seg[0] for seg in strips[b]], [seg[1] for seg in strips[a]], atol=1e-6)


def test_blueprint_and_web_viewer(run):
    assert RrdReader(run["path"]).blueprints(), "the default blueprint is stored with the recording"
    served = run["served"]
    assert served["url"].startswith("http://127.0.0.1:")
    assert b"<html" in served["html"].lower()
    assert served["listen"] == {"127.0.0.1"}  # web viewer and gRPC proxy: local only


CHILD = textwrap.dedent("""
    import sys
    from pathlib import Path
    from flipviz.training.config import TrainConfig
    from flipviz.training.events import Observer
    from flipviz.training.trainer import Trainer
    from flipviz.viz.rerun.observer import camera_paths, has_footer, make_rerun_observer

    class Say(Observer):
        def on_step(self, e):
            print(e.step, flush=True)

    cfg = TrainConfig.from_settings(scene="chair", res=32, steps=1000, log_every=1, images_every=0, batch_rays=256,
                      out=Path(sys.argv[1]), checkpoint_every=1, mirror_plane="official")
    trainer = Trainer(cfg)
    trainer.add_observer(make_rerun_observer(cfg, trainer.run_dir, flush_every_s=0.0))
    trainer.add_observer(Say())
    trainer.run()
""")


@pytest.mark.slow
def test_killed_run_leaves_a_readable_recording(tmp_path):
    out = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(out)], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        for line in child.stdout:
            if int(line) >= 3:
                break
        child.send_signal(signal.SIGKILL)  # no on_end, no footer
    finally:
        child.kill()
        child.wait(30)
    assert child.returncode == -signal.SIGKILL
    path = out / "recording.rrd"
    rrd = read_rrd(path)
    assert "/world/sphere" in rrd and len([p for p in rrd if p.startswith("/world/cameras/input/")]) == 8
    assert sorted(rows_by_step(rrd["/curves/train/loss"], "Scalars:scalars"))[:3] == [1, 2, 3]
    # Issue 44: what a reader and the viewer get: every chunk decodes (Rerun's own verifier, its footer check
    # aside), and the killed file lacks only its footer, which `rerun rrd verify` reports.
    assert rrd_verify(path, "--check-footers", "false").returncode == 0
    assert not has_footer(path) and "footer" in rrd_verify(path).stdout + rrd_verify(path).stderr
    # The run resumed in its folder finalises it: every recording there then verifies in full.
    resumed = TrainConfig.from_settings(
        scene="chair", res=32, steps=1000, batch_rays=256, images_every=0, mirror_plane="official", out=out, resume=out
    )
    trainer = Trainer(resumed)
    observer = make_rerun_observer(resumed, trainer.run_dir)
    trainer.close()
    observer.close()
    assert has_footer(path) and rrd_verify(path).returncode == 0, rrd_verify(path).stderr
    again = read_rrd(path)  # the same rows, compacted
    assert sorted(rows_by_step(again["/curves/train/loss"], "Scalars:scalars")) == sorted(
        rows_by_step(rrd["/curves/train/loss"], "Scalars:scalars")
    )


def rrd_verify(path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rerun_cli", "rrd", "verify", *args, str(path)], capture_output=True, text=True
    )


def test_the_finished_recording_is_compacted(tmp_path):
    """Issue 26: a run's live log is a small chunk per step and entity (a default chair run: 1849
    chunks, read 3.5x slower than compacted). The finished file is compacted in place, rows intact."""
    from flipviz.viz.rerun.observer import optimize_recording

    path = tmp_path / "recording.rrd"
    rec = rr.RecordingStream("flipviz-test", recording_id="compact")
    rec.save(str(path))
    for step in range(300):  # one chunk per row, as a live run writes them
        rec.set_time("step", sequence=step)
        rec.log("curves/psnr", rr.Scalars(float(step)))
        rec.flush(timeout_sec=5.0)
    rec.disconnect()
    assert len(read_rrd(path)["/curves/psnr"]) > 100  # (the premise: many small chunks)
    assert optimize_recording(path) is True
    batches = read_rrd(path)["/curves/psnr"]
    assert len(batches) <= 2 and sorted(rows_by_step(batches, "Scalars:scalars")) == list(range(300))
    assert not list(tmp_path.glob("*.optimizing"))


def test_a_recording_that_cannot_be_compacted_is_kept_as_it_is(tmp_path, caplog):
    from flipviz.viz.rerun.observer import optimize_recording

    path = tmp_path / "recording.rrd"
    path.write_bytes(b"not an rrd file" * 100)
    assert optimize_recording(path) is False
    assert path.read_bytes() == b"not an rrd file" * 100 and not list(tmp_path.glob("*.optimizing"))
    assert "kept as written" in caplog.text


@pytest.mark.slow
def test_the_field_is_recorded_as_gaussian_splats(run, tmp_path):
    """Issue 21: the recording holds the 3D model: the field's solid cells as Gaussian splats at every
    n-th periodic render and at the end, one scale for all, each with its cell's colour and opacity."""
    from flipviz.viz.splats import SIGMA_PER_CELL

    centers = rows_by_step(run["rrd"]["/world/field"], "GaussianSplats3D:centers")
    assert sorted(centers) == [IMAGES_EVERY, STEPS]  # splats_every=1: each ImagesEvent; the end is logged once
    cfg = TrainConfig.from_settings(
        scene="chair",
        res=32,
        steps=200,
        images_every=100,
        batch_rays=512,
        out=tmp_path / "run",
        checkpoint_every=0,
        mirror_plane="official",
    )
    trainer = Trainer(cfg)  # long enough for solid cells
    obs = make_rerun_observer(cfg, trainer.run_dir, bake=trainer.point_cloud, splats_every=2)
    trainer.add_observer(obs)
    try:
        trainer.run()
    finally:
        obs.close()
    batches = read_rrd(trainer.run_dir / "recording.rrd")["/world/field"]
    centers = rows_by_step(batches, "GaussianSplats3D:centers")
    assert sorted(centers) == [200]  # the 2nd ImagesEvent (step 100 was the 1st), the end: the same step, once
    baked = trainer.point_cloud()
    solid = baked["solid"]
    got = np.asarray(centers[200], np.float32)
    assert len(got) == int(solid.sum()) > 100
    assert np.allclose(np.sort(got[:, 2]), np.sort(baked["points"][solid][:, 2]))
    (scale,) = rows_by_step(batches, "GaussianSplats3D:scales")[200]
    assert scale == pytest.approx([SIGMA_PER_CELL * float(baked["cell"])] * 3)
    colours = np.asarray(rows_by_step(batches, "GaussianSplats3D:colors")[200], np.uint32)
    alpha = (colours & 0xFF).astype(np.float32) / 255.0  # Rerun's RGBA as 0xRRGGBBAA
    assert np.allclose(np.sort(alpha), np.sort(baked["alpha"][solid]), atol=1 / 255 + 1e-6)
