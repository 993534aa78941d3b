"""The structure metrics on images with known answers: silhouette IoU, PSNR inside the object, depth
error against the ray caster's true depth; and that a run reports them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from flipviz.data.cameras import Camera, look_at
from flipviz.data.raycast import render_depth
from flipviz.training.evaluate import depth_abs_error, masked_psnr, silhouette_iou, structure_scores

N = 400


def disc(cx: float, cy: float, r: float) -> np.ndarray:
    y, x = np.mgrid[0:N, 0:N] + 0.5
    return ((x - cx) ** 2 + (y - cy) ** 2 <= r**2).astype(np.float32)


def lens_iou(r: float, d: float) -> float:
    """IoU of two discs of radius r whose centres are d apart (closed form)."""
    lens = 2 * r**2 * np.arccos(d / (2 * r)) - 0.5 * d * np.sqrt(4 * r**2 - d**2)
    return lens / (2 * np.pi * r**2 - lens)


@pytest.mark.parametrize("shift", [0.0, 20.0, 60.0, 100.0])
def test_iou_of_a_disc_and_a_shifted_disc(shift):
    a, b = disc(200, 200, 80), disc(200 + shift, 200, 80)
    assert silhouette_iou(a, b) == pytest.approx(lens_iou(80, shift), abs=0.01)
    assert silhouette_iou(np.zeros((N, N)), np.zeros((N, N))) == 1.0
    assert silhouette_iou(np.zeros((N, N)), a) == 0.0  # an empty render of a real object: nothing


def test_object_psnr_sees_only_the_object():
    alpha = disc(200, 200, 80)
    gt = np.ones((N, N, 3), np.float32)
    gt[alpha > 0.5] = 0.3
    pred = gt.copy()
    pred[alpha > 0.5] += 0.1  # error 0.1 inside the object: 20 dB there
    pred[:10, :10] = 0.0  # an error outside both silhouettes does not count
    assert masked_psnr(pred, gt, alpha > 0.5) == pytest.approx(20.0, abs=1e-4)
    # a render that keeps the object's space white: the object's PSNR is that of white against it
    white = np.ones_like(gt)
    s = structure_scores(white, gt, np.zeros((N, N)), alpha)
    assert s["iou"] == 0.0 and s["psnr_object"] == pytest.approx(-10 * np.log10(0.7**2), abs=1e-3)
    assert "depth_abs" not in s and structure_scores(white, gt, alpha, None) == {}


def test_depth_of_a_known_plane_and_its_error():
    floor = trimesh.creation.box(extents=(20.0, 20.0, 0.1))  # top face at z = 0.05
    cam = Camera(look_at(np.array([0.0, 0.0, 4.05]), np.zeros(3), up=np.array([0.0, 1.0, 0.0])), 64, 48, 40.0)
    depth = render_depth(floor, cam)
    _, d = cam.rays()
    cos = -d[:, 2].reshape(48, 64)  # the ray's angle to the straight-down axis
    assert np.allclose(depth, 4.0 / cos, rtol=1e-5)
    sky = Camera(
        look_at(np.array([0.0, 0.0, 4.05]), np.array([0.0, 0.0, 9.0]), up=np.array([0.0, 1.0, 0.0])), 8, 8, 6.0
    )
    assert np.isinf(render_depth(floor, sky)).all()
    alpha = np.ones((48, 64), np.float32)
    assert depth_abs_error(depth + 0.25, depth, alpha) == pytest.approx(0.25, abs=1e-5)
    alpha[:, :32] = 0.0  # only the silhouette counts
    off = depth.copy()
    off[:, :32] += 5.0
    assert depth_abs_error(off, depth, alpha) == pytest.approx(0.0, abs=1e-6)


def test_coverage_of_the_protocols_rings():
    """On the ring with the chair's plane (x = 0): configuration 1 mirrors land on the unobserved views
    (7 of 8 exactly, one 19 degrees off: every view within 30), configuration 3 covers only 2 of 8;
    n and n + 4 are the same half ring turned by 180 degrees, so they cover alike."""
    from flipviz.data import load_builtin
    from flipviz.data.protocol import make_split
    from flipviz.geometry.coverage import coverage, nearest_mirror_deg
    from flipviz.geometry.mirror import make_mirror_set

    scene = load_builtin("chair", res=16)
    cov = {}
    for n in range(1, 9):
        split = make_split(scene, n)
        ms = make_mirror_set(split.inputs, "official", scene.symmetry_plane, scene.center, scene.up, pose="lookat")
        cov[n] = coverage([v.camera for v in split.tests], [v.camera for v in ms.views], ms.sphere.center)
        assert len(cov[n]["per_view_deg"]) == 8
    assert cov[1]["within_30"] == 1.0 and sum(a < 1e-6 for a in cov[1]["per_view_deg"]) == 7
    assert cov[3]["within_30"] == 0.25 and cov[3]["mean_angle_deg"] > 40
    for n in range(1, 5):
        assert cov[n]["per_view_deg"] == pytest.approx(cov[n + 4]["per_view_deg"], abs=1e-6)
    tests = [v.camera for v in make_split(scene, 1).tests]
    assert np.allclose(nearest_mirror_deg(tests, tests, np.zeros(3)), 0.0, atol=1e-5)  # a test view is its own mirror
    assert np.isinf(nearest_mirror_deg(tests, [], np.zeros(3))).all()
