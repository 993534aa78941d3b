"""The mirror plane as a parameter of training (training/flip.py: MirrorPlane, --refine-plane)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flipviz.data.builtin import load_builtin
from flipviz.data.cameras import rays_from_c2w
from flipviz.data.dataset import Plane
from flipviz.data.protocol import make_split
from flipviz.data.rays import RayBank
from flipviz.geometry.mirror import exact_reflected_camera, initial_mirrored_camera, make_mirror_set
from flipviz.geometry.sphere import fit_camera_sphere
from flipviz.geometry.symmetry import plane_error
from flipviz.model import GridConfig, ModelConfig, RadianceModel
from flipviz.model.fit import fit
from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer
from flipviz.training.flip import MirrorPlane
from flipviz.training.setup import build_run
from flipviz.training.trainer import Trainer

TRUE = Plane(np.zeros(3), np.array([1.0, 0.0, 0.0]))  # the chair's


def turned(plane: Plane, deg: float, offset: float) -> Plane:
    """`plane` turned by `deg` about the vertical and moved by `offset` along its normal."""
    n = Rotation.from_euler("z", deg, degrees=True).apply(plane.normal)
    return Plane(plane.point + offset * plane.normal, n)


def test_the_plane_motion_keeps_mirrored_cameras_exact_and_moves_lookat_ones_rigidly():
    """c2w(P) = S_P S_P0 c2w(P0): a camera reflected through P0 becomes the one reflected through P."""
    scene = load_builtin("chair", 16)
    cams = [v.camera for v in make_split(scene, 1).inputs]
    p0, p1 = turned(TRUE, 4.0, 0.03), turned(TRUE, -2.0, -0.05)
    mp = MirrorPlane(p0)
    with torch.no_grad():  # move the parameters onto p1: tilt along (u, v), shift along n0
        n1 = torch.as_tensor(p1.normal, dtype=torch.float32)
        k = 1.0 / float(n1 @ mp.n0)
        mp.tilt.copy_(torch.stack([k * (n1 @ mp.u), k * (n1 @ mp.v)]))
        mp.shift.copy_(torch.as_tensor(float((p1.point - p0.point) @ p1.normal) / float(p1.normal @ p0.normal)))
    deg, off = plane_error(mp.plane(), p1)
    assert deg < 1e-4 and off < 1e-5, (deg, off)
    motion = mp.motion().detach().double().numpy()
    for c in cams:
        moved = motion @ exact_reflected_camera(c, p0).c2w
        assert np.allclose(moved, exact_reflected_camera(c, p1).c2w, atol=1e-5)
    sphere = fit_camera_sphere(cams)
    look = [motion @ initial_mirrored_camera(c, p0, sphere).c2w for c in cams]
    assert all(
        np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-5) and np.linalg.det(m[:3, :3]) > 0 for m in look
    )
    assert np.allclose(MirrorPlane(p0).motion().detach().numpy(), np.eye(4), atol=1e-6)  # it starts at P0


@pytest.fixture(scope="module")
def known_field():
    """A field that knows the whole chair (all 16 ring views, 32 px): mirrored views rendered from it
    agree with the flipped inputs exactly when they are posed through the true plane."""
    scene = load_builtin("chair", 32)
    split = make_split(scene, 1)
    torch.manual_seed(0)
    model = RadianceModel(
        ModelConfig(field=GridConfig(grid_res=(32, 48), upsample_at=(0.3,)), n_samples=48),
        scene.bbox,
        scene.near,
        scene.far,
        with_beta=False,
    )
    fit(model, split.inputs + split.tests, 400, batch_rays=2048)
    return model, split.inputs


def plane_gradient(model: RadianceModel, inputs, start: Plane) -> MirrorPlane:
    """The mirrored rays' photometric loss, back-propagated to a MirrorPlane starting at `start`."""
    ms = make_mirror_set(inputs, start, pose="reflect")
    bank = RayBank.from_images(ms.cameras, [v.rgb for v in ms.views], "cpu")
    c2w = torch.as_tensor(np.stack([c.c2w for c in ms.cameras]), dtype=torch.float32)
    mp = MirrorPlane(start)
    idx = bank.sample(8192, torch.Generator().manual_seed(0))
    o, d = rays_from_c2w((mp.motion() @ c2w)[bank.view[idx]], bank.dirs_cam[idx])
    loss = (model.render_rays(o, d, training=False)["rgb"] - bank.rgb[idx]).pow(2).mean()
    loss.backward()
    return mp


@pytest.mark.parametrize("deg, offset", [(3.0, 0.0), (-3.0, 0.0), (0.0, 0.06), (0.0, -0.06)])
@pytest.mark.slow
def test_the_plane_gradient_points_back_to_the_true_plane(known_field, deg, offset):
    model, inputs = known_field
    start = turned(TRUE, deg, offset)
    mp = plane_gradient(model, inputs, start)
    g_tilt, g_shift = mp.tilt.grad, mp.shift.grad
    assert float(g_tilt.norm()) > 0 and float(g_shift.abs()) > 0
    before = plane_error(mp.plane(), TRUE)
    with torch.no_grad():  # a small step down the gradient of the perturbed part brings the plane closer
        if deg:
            mp.tilt -= 0.01 * g_tilt / g_tilt.norm()
        else:
            mp.shift -= 0.005 * torch.sign(g_shift)
    after = plane_error(mp.plane(), TRUE)
    k = 0 if deg else 1
    assert after[k] < before[k] - (0.3 if deg else 0.003), (before, after)


@pytest.mark.slow
def test_a_symmetric_object_keeps_its_exact_plane(tmp_path):
    """Started from the chair's exact plane, refinement leaves it there (0.3 deg, 0.01 units). Measured: 0.11° /
    0.000 at 64 px and 400 steps, 0.08° / 0.001 at the defaults (100 px, 600); at 48 px and 300 steps it drifts
    0.37°: the lighting is not symmetric, and a coarse model lets the photometric optimum wander."""
    tr = Trainer(
        TrainConfig.from_settings(
            scene="chair",
            res=64,
            steps=400,
            mirror_plane="scene",
            out=tmp_path / "run",
            no_rrd=True,
            images_every=0,
            checkpoint_every=0,
        )
    )
    m = tr.run()
    deg, off = plane_error(tr.flip.current_plane(), TRUE)
    assert m["plane"]["refined_error_deg"] == pytest.approx(deg) and deg < 0.3 and off < 0.01, (deg, off)
    assert m["plane"]["error_deg"] < 1e-9  # it started exact


@pytest.mark.slow
def test_refinement_recovers_a_plane_turned_5_degrees_and_moved_5_hundredths(tmp_path):
    """A shortened default run (Flip+U, 64 px, 400 steps: 25 s, where 100 px and 600 steps took 3 min on a busy
    CI machine) on the chair, its plane started 5° and 0.05 off. It ends 0.48° / 0.002 off here."""
    start = turned(TRUE, 5.0, 0.05)
    arg = ",".join(map(str, start.point)) + ";" + ",".join(map(str, start.normal))
    tr = Trainer(
        TrainConfig.from_settings(
            scene="chair",
            mirror_plane=arg,
            out=tmp_path / "run",
            no_rrd=True,
            images_every=0,
            checkpoint_every=0,
            res=64,
            steps=400,
        )
    )
    assert tr.cfg.flip.refine_plane  # on by default
    tr.run()
    deg, off = plane_error(tr.flip.current_plane(), TRUE)
    assert deg < 1.0 and off < 0.015, (deg, off)  # from 5.00° / 0.050


@pytest.mark.parametrize("field", ["grid", "nerf"])
def test_both_fields_move_the_plane_and_a_resumed_run_keeps_it(tmp_path, field):
    """The plane is a parameter whatever the field; --no-refine-plane keeps it fixed; a checkpoint holds it."""
    start = turned(TRUE, 3.0, 0.0)
    arg = ",".join(map(str, start.point)) + ";" + ",".join(map(str, start.normal))
    kw = dict(
        scene="chair",
        res=16,
        steps=6,
        batch_rays=128,
        n_samples=16,
        field=field,
        mirror_plane=arg,
        no_rrd=True,
        images_every=0,
    )
    tr = Trainer(TrainConfig.from_settings(**kw, out=tmp_path / "a"))
    m = tr.run()
    assert m["plane"]["refined_change_deg"] > 0.0 or m["plane"]["refined_change_offset"] > 0.0
    moved = tr.flip.current_plane()
    again = Trainer(TrainConfig.from_settings(**kw, out=tmp_path / "b", resume=tmp_path / "a"))
    assert plane_error(again.flip.current_plane(), moved) == pytest.approx((0.0, 0.0), abs=1e-6)
    fixed = Trainer(TrainConfig.from_settings(**kw, out=tmp_path / "c", refine_plane=False))
    assert "refined" not in fixed.run()["plane"] and fixed.flip.current_plane() is None


SHORT_AUTO = dict(  # a short --mirror-plane auto run on the chair whose field shows a surface at its join
    scene="chair",
    res=24,
    steps=160,
    batch_rays=256,
    n_samples=24,
    grid_res=(16,),
    images_every=0,
    no_rrd=True,
    disagreement_limit=float("inf"),
    estimate_after=40,  # a quarter of this short run (150 steps by default)
)


@pytest.mark.slow
def test_auto_estimates_the_plane_from_the_runs_own_field_then_the_mirrors_join(tmp_path):
    """--mirror-plane auto (issue 20 item 3): the run trains its inputs alone for --estimate-after steps,
    estimates the plane from that field (no separate fit), and the mirrored views join at that step, with
    their schedules counted from it; a resumed run reads the estimate back and keeps the same join. A run
    whose first quarter is shorter than --estimate-after takes the separate fit's plane and trains its
    mirrors from step 0 (a younger field's estimate would be doubted: a 300-step chair run's, at step 75,
    was 52.9 degrees off)."""
    import json

    kw = SHORT_AUTO
    assert TrainConfig().flip.estimate_after == 150
    said: list[str] = []  # issue 45: what setup does before the first event, in words (flipviz train prints it)
    tr = Trainer(TrainConfig.from_settings(**kw, out=tmp_path / "a", checkpoint_every=80), on_phase=said.append)
    K = 40
    assert said[0] == "warm-up for the auto plane: step 0 / 40 of the inputs alone", said
    assert said[-1].startswith("estimating the mirror plane from the warmed-up field"), said
    assert tr.cfg.flip.mirror_plane == "auto"
    assert tr.step == K and tr.plane_estimate.meta["field_steps"] == K and "fit_steps" not in tr.plane_estimate.meta
    assert tr.training.mirror_ids and tr.flip.start == K and tr.spec.mirrors  # kept (--unconfident-plane use)
    assert tr.flip.objective.nll_start == K + int(0.2 * (160 - K)) and tr.flip.ba_start == K + int(0.5 * (160 - K))
    first_mirror = min(tr.training.mirror_ids)
    gen = torch.Generator().manual_seed(0)
    assert not bool((tr.training.bank.view[tr.flip.sample(4000, gen, K - 1)] >= first_mirror).any())  # before the join
    assert bool((tr.training.bank.view[tr.flip.sample(4000, gen, K)] >= first_mirror).any())  # from it on
    plane = tr.flip.current_plane()
    assert plane_error(plane, tr.plane_estimate.plane) == pytest.approx((0.0, 0.0), abs=1e-6)  # refinement starts at it
    m = tr.run()
    assert m["status"] == "finished" and m["plane"]["estimate_seconds"] == tr.plane_estimate.seconds
    saved = json.loads((tmp_path / "a" / "plane.json").read_text())
    assert saved["meta"]["field_steps"] == K
    again = Trainer(
        TrainConfig.from_settings(**kw, out=tmp_path / "b", resume=tmp_path / "a")
    )  # read back, not estimated again
    assert again.plane_estimate.to_dict() == saved, (again.plane_estimate.to_dict(), saved)
    assert again.flip.start == K and again.step == tr.step
    again.close()
    fit = tmp_path / "fit.json"  # the separate fit's estimate, written by the young run, read by the short one
    young = Trainer(
        TrainConfig.from_settings(**{**kw, "steps": 8, "estimate_after": 2}, out=tmp_path / "d", plane_file=fit)
    )  # no surface yet
    assert young.step == 2 and young.flip.start == 2 and young.plane_estimate.meta["fit_steps"] > 0  # a separate fit
    young.close()
    short = Trainer(
        TrainConfig.from_settings(**{**kw, "steps": 159}, out=tmp_path / "e", plane_file=fit)
    )  # 40 steps > a quarter of 159
    assert short.step == 0 and short.flip.start == 0 and short.plane_estimate.meta["fit_steps"] > 0
    assert short.training.mirror_ids and short.spec.mirrors  # the mirrors train from step 0
    short.close()
    given = TrainConfig.from_settings(**{**kw, "estimate_after": 0}, out=tmp_path / "c")
    fitted = build_run(given, tr.scene, tmp_path / "a" / "plane.json")
    assert fitted.flip.warm_up == 0 and fitted.flip.start == 0  # --estimate-after 0, the estimate given: mirrors from 0


@pytest.mark.slow
def test_the_fields_learning_rate_decays_again_from_the_step_the_mirrors_join(tmp_path):
    """--join-lr restart: the side the mirrors bring is learnt from the full lr (the field's decay counts
    again from --estimate-after); continue keeps one decay over the run; a field restarted after the
    agreement gate's drop counts from its own start, as before."""
    kw = dict(**SHORT_AUTO, log_every=1, checkpoint_every=0, plane_file=tmp_path / "plane.json")  # one estimate
    lrs: dict[str, dict[int, float]] = {}
    for join_lr in ("restart", "continue"):
        tr = Trainer(TrainConfig.from_settings(**kw, join_lr=join_lr, out=tmp_path / join_lr))
        assert tr.step == 40 and tr.spec.mirrors  # the mirrors joined: the lr of the steps from here
        seen = lrs[join_lr] = {}
        tr.add_observer(
            type(
                "Lr", (Observer,), {"on_step": lambda self, e, seen=seen: seen.update({e.step: e.scalars["lr_field"]})}
            )()
        )
        tr.run()
    lr0 = tr.model.make_optimizer().param_groups[0]["lr0"]
    assert lrs["restart"][41] == pytest.approx(lr0)  # step index 40: the first with the mirrors
    assert lrs["continue"][41] == pytest.approx(lr0 * 0.1 ** (40 / 160))
    assert lrs["restart"][160] == pytest.approx(lrs["continue"][160], rel=0.05)  # both end near lr0 / 10
    flip = Trainer(TrainConfig.from_settings(**kw, out=tmp_path / "drop")).flip
    assert flip.field_lr(10) == (10, 160) and flip.field_lr(50) == (10, 120)
    flip.dropped_at = 60  # the gate dropped the mirrors and the field restarted: its own steps again
    assert flip.field_lr(50) == (50, 160)


def test_the_mirrored_poses_follow_the_plane_in_the_world_frame(tmp_path):
    """Issue 42: Flip.poses() moves each mirrored camera by the plane's motion in the world frame,
    S_P S_P0 c2w (not c2w S_P S_P0, the camera frame); the inputs do not move."""
    from flipviz.training.config import TrainConfig
    from flipviz.training.trainer import Trainer

    cfg = TrainConfig.from_settings(
        scene="chair", res=16, grid_res=(16,), n_samples=16, mirror_plane="official", out=tmp_path / "r"
    )
    tr = Trainer(cfg)
    with torch.no_grad():
        tr.flip.plane.tilt.copy_(torch.tensor([0.05, -0.03]))
        tr.flip.plane.shift.fill_(0.04)
    motion = tr.flip.plane.motion().detach()
    poses, init = tr.flip.poses().detach(), tr.training.init_c2w
    mirrors = tr.flip.mirror_ids
    torch.testing.assert_close(poses[mirrors], motion @ init[mirrors], atol=1e-6, rtol=0)
    inputs = [i for i in range(len(init)) if i not in mirrors.tolist()]
    torch.testing.assert_close(poses[inputs], init[inputs])
    tr.close()


def test_the_plane_ramp_makes_its_first_steps_small(tmp_path):
    """--plane-ramp: the plane's learning rate rises from 0, so its first Adam steps (full-size whatever the
    gradient, lr per parameter) are a share of lr; without it the first step moves the shift by about lr."""
    moved = {}
    for ramp in (0.0, 0.1):  # 0.1 of 100 steps: the first step at lr / 10
        tr = Trainer(
            TrainConfig.from_settings(
                scene="chair", res=16, steps=100, batch_rays=64, mirror_plane="official", plane_ramp=ramp,
                plane_lr=1e-2, out=tmp_path / f"ramp{ramp}", no_rrd=True, images_every=0, checkpoint_every=0,
            )
        )  # fmt: skip
        tr._step()
        moved[ramp] = abs(float(tr.flip.plane.shift))
        tr.close()
    assert moved[0.0] > 5e-3, moved  # Adam's first step: of the order of lr (8.3e-3 measured)
    assert moved[0.1] == pytest.approx(moved[0.0] / 10, rel=1e-3), moved  # the ramp's: a tenth of it
