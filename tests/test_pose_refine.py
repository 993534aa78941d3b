"""BARF-style pose refinement: pypose conventions, masking, and recovery of a perturbed pose."""

from __future__ import annotations

import numpy as np
import pypose as pp
import pytest
import torch
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from flipviz.data.cameras import rays_from_c2w
from flipviz.data.rays import RayBank
from flipviz.geometry.poses import rotation_angle_deg
from flipviz.model import GridConfig, ModelConfig, PoseRefiner, RadianceModel
from flipviz.model.fit import fit


def mse(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (rgb - target).pow(2).mean()


def lr_at(ref: PoseRefiner, step: int) -> float:
    opt = ref.make_optimizer()
    ref.adjust_lr(opt, step)
    return opt.param_groups[0]["lr"]


pytestmark = pytest.mark.usefixtures("small_torch")


def hat(xi: np.ndarray) -> np.ndarray:
    """4x4 twist matrix of xi = [rho, phi] (translation part first)."""
    rho, phi = xi[:3], xi[3:]
    W = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    T = np.zeros((4, 4))
    T[:3, :3], T[:3, 3] = W, rho
    return T


def test_pypose_se3_ordering_is_translation_then_rotation():
    # pure translation: the first three entries
    m = pp.se3(torch.tensor([0.1, -0.2, 0.3, 0.0, 0.0, 0.0], dtype=torch.float64)).Exp().matrix().numpy()
    assert np.allclose(m[:3, :3], np.eye(3)) and np.allclose(m[:3, 3], [0.1, -0.2, 0.3])
    # pure rotation: the last three entries, an axis-angle vector
    r = np.array([0.2, -0.1, 0.4])
    m = pp.se3(torch.tensor([0, 0, 0, *r], dtype=torch.float64)).Exp().matrix().numpy()
    assert np.allclose(m[:3, :3], Rotation.from_rotvec(r).as_matrix()) and np.allclose(m[:3, 3], 0)
    # general twist: Exp equals the matrix exponential of the twist (translation through V(phi))
    xi = np.array([0.3, 0.1, -0.5, 0.7, -0.2, 0.3])
    lie = pp.se3(torch.tensor(xi, dtype=torch.float64)).Exp()
    assert np.allclose(lie.matrix().numpy(), expm(hat(xi)), atol=1e-10)
    # SE3 storage: [t, q] with the quaternion in x, y, z, w order (scalar last, as scipy)
    data = lie.tensor().numpy()
    assert np.allclose(data[:3], expm(hat(xi))[:3, 3])
    q = Rotation.from_rotvec(xi[3:]).as_quat()  # scipy: x, y, z, w
    assert np.allclose(data[3:], q) or np.allclose(data[3:], -q)


def test_refiner_composes_on_the_camera_side():
    c2w = np.stack([np.eye(4), np.eye(4)])
    c2w[1, :3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    c2w[1, :3, 3] = [1.0, 2.0, 3.0]
    ref = PoseRefiner(c2w, np.array([True, True]), total_steps=10)
    with torch.no_grad():
        ref.xi[1] = torch.tensor([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])  # move along the camera's own x
    out = ref().detach().numpy()
    assert np.allclose(out[0], np.eye(4))
    # the camera's x axis is world +y (rotated 90 deg about z): the centre moves along world +y
    assert np.allclose(out[1, :3, 3], [1.0, 2.5, 3.0], atol=1e-6)
    assert np.allclose(out[1, :3, :3], c2w[1, :3, :3], atol=1e-6)


def test_lr_schedule_is_exponential_from_1e3_to_1e5():
    ref = PoseRefiner(np.eye(4)[None], np.array([True]), total_steps=100)
    assert lr_at(ref, 0) == pytest.approx(1e-3)
    assert lr_at(ref, 50) == pytest.approx(1e-4)
    assert lr_at(ref, 100) == pytest.approx(1e-5)
    assert lr_at(ref, 150) == pytest.approx(1e-5)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        PoseRefiner(np.eye(4), np.array([True]), 10)
    with pytest.raises(ValueError):
        PoseRefiner(np.eye(4)[None].repeat(2, 0), np.array([True]), 10)


def perturb(c2w: np.ndarray, deg: float, trans: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    t = rng.normal(size=3)
    t *= trans / np.linalg.norm(t)
    out = c2w.copy()
    out[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis).as_matrix() @ c2w[:3, :3]
    out[:3, 3] = c2w[:3, 3] + t
    return out


RES = 40


@pytest.fixture(scope="module")
def chair_views():
    """The built-in chair seen from 16 close, wide-angle cameras on two rings (strong parallax,
    so that a rotation is not confused with a sideways translation), rendered at 40 px."""

    from flipviz.data.builtin import render_view
    from flipviz.data.cameras import Camera, View
    from flipviz.geometry.poses import look_at

    focal = 0.5 * RES / np.tan(np.radians(32.5))
    views = []
    for k in range(16):
        az, el = np.radians(22.5 * k), np.radians(15.0 if k % 2 else 45.0)
        eye = 2.7 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cam = Camera(look_at(eye, np.zeros(3)), RES, RES, focal, name=f"c{k}")
        rgb, alpha = render_view("chair", cam)
        views.append(View(cam, rgb, alpha, index=k))
    bbox = np.array([[-0.75, -0.65, -1.25], [0.75, 0.65, 1.25]])
    return bbox, views


@pytest.mark.slow
def test_ba_recovers_a_perturbed_camera(chair_views):
    """Fit the grid on the true views, perturb one pose by 5 deg / 0.1, refine that pose only."""
    bbox, views = chair_views
    cfg = ModelConfig(GridConfig(grid_res=(24, 40), upsample_at=(0.4,), occ_start=40, occ_every=10), n_samples=48)
    model = RadianceModel(cfg, bbox, 1.0, 5.0, False)
    held = views[3]
    fit(model, views, steps=150, batch_rays=1024)
    for p in model.parameters():
        p.requires_grad_(False)

    true = held.camera.c2w
    start = perturb(true, 5.0, 0.1)
    err0 = rotation_angle_deg(start[:3, :3], true[:3, :3])
    assert err0 == pytest.approx(5.0, abs=1e-6)
    steps = 80
    ref = PoseRefiner(np.stack([views[0].camera.c2w, start]), np.array([False, True]), steps, lr=1e-2, lr_end=1e-3)
    opt = ref.make_optimizer()
    bank = RayBank.from_images([held.camera], [held.rgb])
    for step in range(steps):
        ref.adjust_lr(opt, step)
        c2w = ref()[1].expand(len(bank), 4, 4)
        o, d = rays_from_c2w(c2w, bank.dirs_cam)
        loss = mse(model.render_rays(o, d, training=True)["rgb"], bank.rgb)
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = ref().detach().double().numpy()
    err1 = rotation_angle_deg(final[1, :3, :3], true[:3, :3])
    print(f"BA rotation error {err0:.2f} -> {err1:.2f} deg")
    assert err1 <= 0.3 * err0, (err0, err1)
    # the camera with refine=False did not move at all
    assert np.array_equal(final[0], ref.init_c2w[0].double().numpy())
    assert torch.all(ref.xi[0] == 0)


def test_unrefined_poses_do_not_move_under_joint_optimisation(chair_views):
    bbox, views = chair_views
    model = RadianceModel(ModelConfig(GridConfig(grid_res=(16,), upsample_at=()), n_samples=32), bbox, 1.0, 5.0, False)
    cams = views[:3]
    init = np.stack([v.camera.c2w for v in cams])
    ref = PoseRefiner(init, np.array([False, True, False]), 10)
    opt, popt = model.make_optimizer(), ref.make_optimizer()
    bank = RayBank.from_images([v.camera for v in cams], [v.rgb for v in cams])
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        idx = bank.sample(512, gen)
        o, d = rays_from_c2w(ref()[bank.view[idx]], bank.dirs_cam[idx])
        loss = mse(model.render_rays(o, d, training=True)["rgb"], bank.rgb[idx])
        opt.zero_grad(), popt.zero_grad()
        loss.backward()
        opt.step(), popt.step()
    out = ref().detach().numpy()
    assert np.array_equal(out[[0, 2]], ref.init_c2w[[0, 2]].numpy())
    assert not np.allclose(out[1], ref.init_c2w[1].numpy())


def test_bas_poses_are_computed_only_once_it_starts_and_the_run_is_the_same(tmp_path):
    """Before BA's start every twist is 0: Flip.poses() gives the initial poses without calling the refiner
    (pypose's Exp), and the run is the same, value for value, as one that calls it from step 0. A
    checkpoint keeps whether BA is on, and a resumed run goes on calling it."""
    from flipviz.training.config import TrainConfig
    from flipviz.training.trainer import Trainer

    def run(force: bool, out: str) -> tuple[Trainer, list[int]]:
        cfg = TrainConfig.from_settings(
            scene="chair", res=24, batch_rays=256, n_samples=32, grid_res=(24,), images_every=0, log_every=1,
            mirror_plane="official", steps=12, ba_start=0.5, out=tmp_path / out, eval_on_stop=False,
        )  # fmt: skip
        tr = Trainer(cfg)
        calls: list[int] = []
        forward = tr.flip.refiner.forward
        tr.flip.refiner.forward = lambda: calls.append(tr.step) or forward()
        tr.flip.ba_on = tr.flip.ba_on or force
        while tr.step < 12:
            tr._train_step()
        return tr, calls

    lazy, calls = run(False, "lazy")
    always, _ = run(True, "always")
    assert calls and min(calls) == 6  # the refiner from BA's first step on, not before
    assert torch.equal(lazy.flip.refiner.xi, always.flip.refiner.xi) and lazy.flip.refiner.xi.abs().sum() > 0
    for a, b in zip(lazy.model.state_dict().values(), always.model.state_dict().values()):
        assert torch.equal(a, b)
    state = lazy.flip.state_dict()
    assert state["ba_on"] is True
    lazy.flip.ba_on = False
    lazy.flip.load_state_dict(state)
    assert lazy.flip.ba_on
    lazy.close()
    always.close()
