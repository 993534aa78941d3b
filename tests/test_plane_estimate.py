"""--mirror-plane auto: the symmetry plane from the inputs alone, with a confidence."""

from __future__ import annotations

import numpy as np
import pytest

from flipviz.data import Plane, load_builtin, make_split
from flipviz.data.scenes import TURN_YAW_DEG, cached_mesh, symmetry_plane
from flipviz.geometry.mirror import mirror_plane
from flipviz.geometry.sphere import fit_camera_sphere
from flipviz.geometry.symmetry import CONFIDENT, PlaneEstimate, SymmetryVolume, plane_error, search_plane
from flipviz.training.plane_estimate import estimate_or_read, estimate_plane


def test_turned_scenes_keep_an_exact_known_plane_that_official_misses():
    for name in ("chair-turned", "truck-turned"):
        plane = symmetry_plane(name)
        v = np.asarray(cached_mesh(name).vertices)
        d = (v - plane.point) @ plane.normal
        mirrored = v - 2.0 * d[:, None] * plane.normal
        from scipy.spatial import cKDTree

        assert cKDTree(v).query(mirrored)[0].max() < 1e-9, f"{name}: the turned plane is not a symmetry"
    official = mirror_plane(
        "official", [], fit_camera_sphere([v.camera for v in make_split(load_builtin("chair-turned", 32), 1).inputs])
    )
    deg, off = plane_error(official, symmetry_plane("chair-turned"))
    assert deg == pytest.approx(TURN_YAW_DEG) and off > 0.1


def _volume(points: np.ndarray, box: np.ndarray, res: int = 48) -> SymmetryVolume:
    """A volume whose seen surface is `points` and that saw everything (no occlusion)."""
    cell = (box[1] - box[0]) / (res - 1)
    idx = np.clip(np.round((points - box[0]) / cell).astype(int), 0, res - 1)
    surface = np.zeros((res,) * 3, np.float32)
    surface[idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
    return SymmetryVolume(points, surface, np.ones((res,) * 3, bool), box)


def test_search_recovers_a_known_plane_of_points_and_doubts_an_asymmetric_set():
    rng = np.random.default_rng(0)
    truth = Plane(np.array([0.1, -0.2, 0.0]), np.array([np.cos(0.7), np.sin(0.7), 0.0]))
    # an object of blobs on one side of the plane plus their mirror images
    half = np.concatenate([c + 0.06 * rng.standard_normal((150, 3)) for c in rng.uniform(-0.8, 0.8, (8, 3))])
    half = half[(half - truth.point) @ truth.normal > 0.05]
    mirrored = half - 2.0 * ((half - truth.point) @ truth.normal)[:, None] * truth.normal
    box = np.array([[-1.5] * 3, [1.5] * 3])
    est = search_plane(_volume(np.concatenate([half, mirrored]), box), np.array([0.0, 0.0, 1.0]))
    deg, off = plane_error(est.plane, truth)
    assert deg < 1.0 and off < 0.02 and est.confident, (deg, off, est.confidence)
    # blobs with no mirror partner: nothing stands out
    lonely = np.concatenate([c + 0.06 * rng.standard_normal((150, 3)) for c in rng.uniform(-0.8, 0.8, (16, 3))])
    doubt = search_plane(_volume(lonely, box), np.array([0.0, 0.0, 1.0]))
    assert doubt.confidence < est.confidence and not doubt.confident, (doubt.confidence, est.confidence)


@pytest.fixture(scope="module")
def turned_chair():
    return load_builtin("chair-turned", 100)


@pytest.mark.slow
def test_auto_recovers_the_turned_chair_plane(turned_chair):
    """Acceptance: within 3 degrees and 0.05 units, from the 8 inputs of configuration 1 alone."""
    est = estimate_plane(make_split(turned_chair, 1).inputs, turned_chair)
    deg, off = plane_error(est.plane, turned_chair.symmetry_plane)
    assert deg < 3.0 and off < 0.05, (deg, off)
    assert est.confident, est.confidence


@pytest.mark.slow
def test_auto_doubts_the_asymmetric_mug():
    """The mug (a handle and a leaning spoon): measured 0.08-0.20 over the 8 configurations. (The
    lamp, 0.19-0.38, is not reliably doubted: see docs/results/plane.)"""
    import torch

    mug = load_builtin("mug", 100)
    state = torch.get_rng_state()
    est = estimate_plane(make_split(mug, 1).inputs, mug)
    assert torch.equal(torch.get_rng_state(), state)  # the run's random state is its own: dropped Flip == B/L
    assert not est.confident and est.confidence < CONFIDENT, est.confidence
    assert "NOT confident" in est.summary()


def test_a_resumed_run_reads_its_estimate_back(tmp_path, turned_chair):
    est = PlaneEstimate(
        Plane(np.array([0.1, 0.2, 0.3]), np.array([0.0, 1.0, 0.0])), 0.4, 0.9, 0.8, [0.0, 1.0], [0.5, 0.6], 3.0
    )
    path = tmp_path / "plane.json"
    path.write_text(__import__("json").dumps(est.to_dict()))
    back = estimate_or_read([], turned_chair, "cpu", 0, path)  # no inputs: it must not estimate
    assert np.allclose(back.plane.normal, est.plane.normal) and back.confidence == est.confidence
    shared = estimate_or_read([], turned_chair, "cpu", 0, tmp_path / "absent.json", path)  # --plane-file: read, too
    assert np.allclose(shared.plane.point, est.plane.point) and shared.confidence == est.confidence
    path.write_text("{}")
    from flipviz.errors import UserError

    with pytest.raises(UserError, match="cannot read the estimated plane"):
        estimate_or_read([], turned_chair, "cpu", 0, path)


@pytest.mark.parametrize("confidence", [CONFIDENT - 0.01, CONFIDENT])
def test_an_unconfident_plane_is_dropped_unless_the_user_keeps_it(tmp_path, turned_chair, confidence):
    """Flip+U with auto: below the threshold the run trains on the inputs only (no mirrored ray, no BA,
    beta^2 on no ray: B/L's training set), unless --unconfident-plane use; at it, the mirrors stay."""

    from flipviz.training.config import TrainConfig
    from flipviz.training.setup import build_run

    est = PlaneEstimate(turned_chair.symmetry_plane, confidence, 0.9, 0.8, [0.0], [0.5], 3.0)
    saved = tmp_path / "plane.json"
    saved.write_text(__import__("json").dumps(est.to_dict()))
    cfg = TrainConfig.from_settings(scene="chair-turned", method="flip+u", res=100, steps=10, out=tmp_path / "run")
    dropped, kept = (build_run(cfg.with_settings(unconfident_plane=u), turned_chair, saved) for u in ("drop", "use"))
    bl = build_run(cfg.with_settings(method="bl"), turned_chair)
    assert kept.training.mirror_ids and kept.flip.refiner is not None and kept.spec.uncertain_mirrors
    if confidence >= CONFIDENT:
        assert dropped.training.mirror_ids == kept.training.mirror_ids
        return
    assert dropped.estimate is not None and not dropped.estimate.confident
    assert not dropped.training.mirror_ids and dropped.flip.refiner is None and not dropped.spec.uses_beta
    assert len(dropped.training.views) == len(bl.training.views) == 8
    assert np.array_equal(dropped.training.init_c2w.numpy(), bl.training.init_c2w.numpy())


def test_the_estimates_point_lies_on_its_plane_when_the_surface_centroid_does_not():
    """Issue 42: the estimate's point is the surface centroid projected onto the plane. With an unmatched
    blob on one side (the centroid off the plane), a point reflected to the far side instead is off it."""
    rng = np.random.default_rng(1)
    truth = Plane(np.array([0.1, -0.2, 0.0]), np.array([np.cos(0.7), np.sin(0.7), 0.0]))
    half = np.concatenate([c + 0.06 * rng.standard_normal((150, 3)) for c in rng.uniform(-0.8, 0.8, (8, 3))])
    half = half[(half - truth.point) @ truth.normal > 0.05]
    mirrored = half - 2.0 * ((half - truth.point) @ truth.normal)[:, None] * truth.normal
    extra = truth.point + 0.7 * truth.normal + [0, 0, 0.5] + 0.03 * rng.standard_normal((40, 3))  # no partner
    pts = np.concatenate([half, mirrored, extra])
    assert abs((pts.mean(0) - truth.point) @ truth.normal) > 0.02  # the premise: the centroid is off the plane
    est = search_plane(_volume(pts, np.array([[-1.5] * 3, [1.5] * 3])), np.array([0.0, 0.0, 1.0]))
    deg, off = plane_error(est.plane, truth)
    assert deg < 2.5 and off < 0.01, (deg, off)


def test_a_voxel_just_behind_the_surface_an_input_saw_counts_as_seen_and_one_far_behind_does_not():
    """Issue 42: what the inputs saw reaches two voxels behind their first surface along each ray."""
    from flipviz.data.cameras import Camera, View, look_at
    from flipviz.training.plane_estimate import DEPTH_RES, symmetry_volume

    class Wall:  # every pixel of every input sees a surface at depth 4
        def render_image(self, cam):
            return {"opacity": np.ones((cam.height, cam.width)), "depth": np.full((cam.height, cam.width), 4.0)}

    cam = Camera(look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3)), DEPTH_RES, DEPTH_RES, DEPTH_RES * 2.0)
    box = np.array([[-1.0] * 3, [1.0] * 3])
    vol = symmetry_volume(Wall(), [View(cam, np.ones((DEPTH_RES, DEPTH_RES, 3), np.float32))], box, res=21)
    cell = 2.0 / 20
    seen = vol.seen.reshape(-1)
    lattice = vol.lattice()
    on_axis = (np.abs(lattice[:, 0]) < 1e-9) & (np.abs(lattice[:, 2]) < 1e-9)  # the voxels on the camera's axis
    depth = lattice[:, 1] + 5.0  # distance from the camera along its axis
    assert seen[on_axis & (np.abs(depth - 4.0 - cell) < 1e-6)].all()  # one voxel behind the surface
    assert not seen[on_axis & (depth > 4.0 + 3.5 * cell)].any()  # well behind it
