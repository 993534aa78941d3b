"""Geometry layer (paper Sec. IV-A): sphere fit, reflections, initial and exact mirrored poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flipviz.data.cameras import Camera, View
from flipviz.data.dataset import DatasetError, Plane
from flipviz.geometry import (
    exact_reflected_camera,
    fit_camera_sphere,
    fit_sphere,
    flip_image,
    initial_mirrored_camera,
    is_proper_rotation,
    look_at,
    make_mirror_set,
    mirror_cameras_for_plane,
    mirror_plane,
    parse_plane,
    pose_errors,
    project_to_sphere,
    reflect_points,
    reflection_matrix,
    rotation_angle_deg,
)
from flipviz.geometry.sphere import Sphere

RING_AZ = np.radians(np.arange(16) * 22.5)


def ring_camera(
    az: float, elev_deg: float = 30.0, radius: float = 4.0, target=(0.0, 0.0, 0.0), name: str = ""
) -> Camera:
    e = np.radians(elev_deg)
    eye = np.asarray(target) + radius * np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)])
    return Camera(look_at(eye, target), width=8, height=6, focal=10.0, name=name)


def half_ring(elev_deg: float = 30.0, target=(0.0, 0.0, 0.0), start: int = 0) -> list[Camera]:
    return [
        ring_camera(RING_AZ[(start + j) % 16], elev_deg, target=target, name=f"r{(start + j) % 16}") for j in range(8)
    ]


def views_of(cams: list[Camera]) -> list[View]:
    rng = np.random.default_rng(0)
    return [
        View(
            c,
            rng.random((c.height, c.width, 3), dtype=np.float32),
            rng.random((c.height, c.width), dtype=np.float32),
            index=i,
        )
        for i, c in enumerate(cams)
    ]


# ---------------------------------------------------------------- sphere


def test_sphere_fit_recovers_noisy_sphere():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    center, r = np.array([0.3, -0.7, 1.2]), 2.5
    pts = center + r * d + rng.normal(scale=1e-3, size=d.shape)
    s = fit_sphere(pts)
    assert np.linalg.norm(s.center - center) < 3e-3
    assert abs(s.radius - r) < 3e-3
    # view directions are only a tie-breaker: they do not change a well-posed fit
    s2 = fit_sphere(pts, view_dirs=rng.normal(size=pts.shape))
    np.testing.assert_allclose(s2.center, s.center)


def test_sphere_fit_coplanar_ring_both_ways():
    cams = half_ring(elev_deg=30.0)
    centers = np.stack([c.center for c in cams])
    # without view directions: the circle's own centre (minimum |centre - centroid|)
    s = fit_sphere(centers)
    np.testing.assert_allclose(s.center, [0.0, 0.0, 2.0], atol=1e-9)
    assert s.radius == pytest.approx(2.0 * np.sqrt(3.0), abs=1e-9)
    # with view directions: the sphere through the circle centred where the cameras look
    dirs = np.stack([-c.c2w[:3, 2] for c in cams])
    s = fit_sphere(centers, dirs)
    np.testing.assert_allclose(s.center, [0.0, 0.0, 0.0], atol=1e-9)
    assert s.radius == pytest.approx(4.0, abs=1e-9)
    # same through the camera helper, and for a target away from the origin
    s = fit_camera_sphere(half_ring(elev_deg=10.0, target=(0.5, -0.2, 0.3)))
    np.testing.assert_allclose(s.center, [0.5, -0.2, 0.3], atol=1e-9)
    assert s.radius == pytest.approx(4.0, abs=1e-9)


def test_sphere_fit_errors():
    with pytest.raises(DatasetError, match="at least 4"):
        fit_sphere(np.eye(3))
    with pytest.raises(DatasetError, match="collinear"):
        fit_sphere(np.outer(np.arange(6.0), [1.0, 2.0, 3.0]))
    with pytest.raises(DatasetError, match="coincide"):
        fit_sphere(np.ones((5, 3)))
    with pytest.raises(DatasetError, match=r"\(N, 3\)"):
        fit_sphere(np.zeros((5, 2)))


def test_lego_orbit_sphere_radius(lego_dir: Path):
    path = lego_dir
    from flipviz.data.blender import load_blender

    scene = load_blender(path, split="test", res=None)
    cams = [v.camera for v in scene.views.values()]
    assert len(cams) == 200
    s = fit_camera_sphere(cams)
    assert s.radius == pytest.approx(4.03, abs=0.01)
    assert np.linalg.norm(s.center) < 0.01


# ---------------------------------------------------------------- reflections and poses


def test_reflection_is_involution():
    rng = np.random.default_rng(2)
    plane = Plane(rng.normal(size=3), rng.normal(size=3))
    p = rng.normal(size=(20, 3))
    np.testing.assert_allclose(reflect_points(reflect_points(p, plane), plane), p, atol=1e-12)
    # points on the plane are fixed, and the reflection moves others by twice their distance
    assert np.allclose(reflect_points(plane.point, plane), plane.point)
    M = reflection_matrix(plane.normal)
    np.testing.assert_allclose(M @ M, np.eye(3), atol=1e-12)
    assert np.linalg.det(M) == pytest.approx(-1.0)
    # the camera-level reflection is an involution too
    cam = ring_camera(0.4)
    twice = exact_reflected_camera(exact_reflected_camera(cam, plane), plane)
    np.testing.assert_allclose(twice.c2w, cam.c2w, atol=1e-12)


def test_project_to_sphere():
    rng = np.random.default_rng(3)
    s = Sphere(np.array([0.1, 0.2, -0.3]), 4.0)
    p = rng.normal(size=(30, 3)) * 3.0
    q = project_to_sphere(p, s)
    np.testing.assert_allclose(np.linalg.norm(q - s.center, axis=1), 4.0)
    # along the ray from the centre: same direction
    u, v = p - s.center, q - s.center
    np.testing.assert_allclose(np.cross(u, v), 0.0, atol=1e-9)
    assert np.all((u * v).sum(1) > 0)
    with pytest.raises(ValueError):
        project_to_sphere(s.center, s)


def test_look_at_convention():
    eye, target = np.array([3.0, 1.0, 2.0]), np.array([0.2, -0.1, 0.3])
    c2w = look_at(eye, target)
    assert is_proper_rotation(c2w[:3, :3])
    np.testing.assert_allclose(c2w[:3, 3], eye)
    fwd = target - eye
    np.testing.assert_allclose(-c2w[:3, 2], fwd / np.linalg.norm(fwd))  # looks along -z
    assert abs(c2w[2, 0]) < 1e-12  # x axis horizontal (up = +z): no roll
    assert c2w[2, 1] > 0  # camera y points upwards
    # degenerate up: still a proper rotation looking at the target
    top = look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    assert is_proper_rotation(top[:3, :3])
    np.testing.assert_allclose(top[:3, 2], [0.0, 0.0, 1.0])
    with pytest.raises(ValueError):
        look_at(eye, eye)


def test_rotation_errors():
    a = np.radians(17.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    R = look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])[:3, :3]
    assert rotation_angle_deg(R, Rz @ R) == pytest.approx(17.0, abs=1e-9)
    assert rotation_angle_deg(R, R) == pytest.approx(0.0, abs=1e-6)
    A, B = np.eye(4), np.eye(4)
    B[:3, :3], B[:3, 3] = Rz, [3.0, 4.0, 0.0]
    rot, trans = pose_errors(A, B)
    assert rot == pytest.approx(17.0) and trans == pytest.approx(5.0)
    assert not is_proper_rotation(reflection_matrix([0.0, 1.0, 0.0]))
    assert not is_proper_rotation(2.0 * np.eye(3))


# ---------------------------------------------------------------- mirror


def test_flip_image():
    img = np.arange(2 * 5 * 3).reshape(2, 5, 3)
    f = flip_image(img)
    assert f.shape == img.shape
    np.testing.assert_array_equal(f[:, 0], img[:, 4])
    np.testing.assert_array_equal(f[1, 1], img[1, 3])  # u -> W-1-u
    np.testing.assert_array_equal(flip_image(f), img)
    np.testing.assert_array_equal(flip_image(img[..., 0]), img[:, ::-1, 0])  # per-pixel maps
    with pytest.raises(ValueError):
        flip_image(np.zeros(4))


def test_parse_plane_and_errors():
    p = parse_plane("0.5,0,1;0,2,0")
    np.testing.assert_allclose(p.point, [0.5, 0.0, 1.0])
    np.testing.assert_allclose(p.normal, [0.0, 1.0, 0.0])
    for bad in ["", "1,2,3", "1,2;0,0,1", "a,b,c;0,0,1", "0,0,0;0,0,0", "0,0,0;1,0,0;1", "0,0,0;nan,0,1"]:
        with pytest.raises(DatasetError, match="mirror plane") as e:
            parse_plane(bad)
        assert "\n" not in str(e.value)
    s = Sphere(np.zeros(3), 4.0)
    with pytest.raises(DatasetError, match="unknown mirror plane"):
        mirror_plane("sideways", half_ring(), s, None)
    with pytest.raises(DatasetError, match="no known symmetry plane"):
        mirror_plane("scene", half_ring(), s, None)
    with pytest.raises(DatasetError, match="bad mirror plane"):
        mirror_plane("1,2;3", half_ring(), s, None)
    assert np.allclose(mirror_plane("0,0,0;0,0,3", half_ring(), s, None).normal, [0.0, 0.0, 1.0])


@pytest.mark.parametrize("start", [0, 2, 5, 14])
def test_opposite_maps_observed_half_onto_unobserved_half(start):
    cams = half_ring(elev_deg=30.0, start=start)
    sphere = fit_camera_sphere(cams)
    plane = mirror_plane("opposite", cams, sphere)
    np.testing.assert_allclose(plane.point, sphere.center, atol=1e-9)
    assert abs(plane.normal[2]) < 1e-12  # vertical
    observed = {(start + j) % 16 for j in range(8)}
    unobserved = [ring_camera(RING_AZ[k]).center for k in range(16) if k not in observed]
    hit = set()
    for m in mirror_cameras_for_plane(cams, plane, sphere, np.array([0.0, 0.0, 1.0]), "lookat"):
        d = [np.linalg.norm(m.center - u) for u in unobserved]
        assert min(d) < 1e-9
        hit.add(int(np.argmin(d)))
    assert len(hit) == 8  # a bijection onto the unobserved half ring


def test_presets_give_proper_poses_on_sphere():
    cams = half_ring(elev_deg=25.0, target=(0.1, 0.2, 0.0), start=3)
    sphere = fit_camera_sphere(cams)
    scene_plane = Plane(np.array([0.1, 0.2, 0.0]), np.array([0.3, 1.0, 0.0]))
    rng = np.random.default_rng(4)
    presets = ["opposite", "official", "scene", "0.1,0.2,0;1,1,0.3"]
    for preset in presets:
        plane = mirror_plane(preset, cams, sphere, scene_plane)
        for cam in cams:
            for m in (initial_mirrored_camera(cam, plane, sphere), exact_reflected_camera(cam, plane)):
                assert is_proper_rotation(m.rotation), (preset, m.name)
            init = initial_mirrored_camera(cam, plane, sphere)
            assert init.name == f"{cam.name}_flip"
            assert np.linalg.norm(init.center - sphere.center) == pytest.approx(sphere.radius)
            np.testing.assert_allclose(-init.c2w[:3, 2], (sphere.center - init.center) / sphere.radius, atol=1e-12)
    # look_at itself, for random eyes and targets
    for _ in range(50):
        assert is_proper_rotation(look_at(rng.normal(size=3) * 3, rng.normal(size=3))[:3, :3])


def test_exact_reflection_flips_the_image_rays():
    """Pixel u of the exact reflected camera sees the reflection of pixel W-1-u's ray."""
    cam = Camera(look_at([3.0, 1.0, 1.5], [0.0, 0.2, 0.1]), width=7, height=5, focal=6.0, name="c")
    plane = Plane(np.array([0.0, 0.3, 0.0]), np.array([0.2, 1.0, 0.1]))
    ref = exact_reflected_camera(cam, plane)
    o, d = cam.rays()
    o2, d2 = ref.rays()
    d = flip_image(d.reshape(5, 7, 3)).reshape(-1, 3)
    M = reflection_matrix(plane.normal)
    np.testing.assert_allclose(d2, d @ M.T, atol=1e-6)
    np.testing.assert_allclose(o2[0], reflect_points(cam.center, plane), atol=1e-6)


def test_initial_equals_exact_for_vertical_plane_through_target():
    cams = half_ring(elev_deg=30.0, start=1)
    sphere = fit_camera_sphere(cams)
    plane = Plane(np.zeros(3), np.array([np.cos(0.7), np.sin(0.7), 0.0]))
    for cam in cams:
        rot, trans = pose_errors(
            initial_mirrored_camera(cam, plane, sphere).c2w, exact_reflected_camera(cam, plane).c2w
        )
        assert rot < 1e-6 and trans < 1e-9
    # a tilted plane does not agree: the look-at pose keeps the camera upright
    tilted = Plane(np.zeros(3), np.array([1.0, 0.0, 0.5]))
    rot, _ = pose_errors(
        initial_mirrored_camera(cams[0], tilted, sphere).c2w, exact_reflected_camera(cams[0], tilted).c2w
    )
    assert rot > 1.0


def test_the_pose_rule_picks_the_reflected_or_the_look_at_camera():
    """`pose` decides each mirrored camera: reflect = the input camera reflected whole (exact for a
    symmetric object), lookat = the paper's pose on the sphere looking at its centre. On a tilted plane
    they differ by degrees, so a swapped rule shows; FlipConfig.mirror_pose reaches the run's mirrors."""
    from types import SimpleNamespace

    from flipviz.training.config import FlipConfig
    from flipviz.training.flip import mirrored_views

    inputs = views_of(half_ring(elev_deg=30.0, start=1))
    tilted = Plane(np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.0, 0.5]))
    up = np.array([0.0, 0.0, 1.0])
    scene = SimpleNamespace(symmetry_plane=None, center=None, up=up)
    for pose in ("reflect", "lookat"):
        ms = make_mirror_set(inputs, tilted, pose=pose)
        run = mirrored_views(FlipConfig(mirror_plane="auto", mirror_pose=pose), inputs, scene, tilted)
        for v, m, r in zip(inputs, ms.views, run.views):
            exact = exact_reflected_camera(v.camera, tilted).c2w
            paper = initial_mirrored_camera(v.camera, tilted, ms.sphere, up).c2w
            want, other = (exact, paper) if pose == "reflect" else (paper, exact)
            for c2w in (m.camera.c2w, r.camera.c2w):
                rot, trans = pose_errors(c2w, want)
                assert rot < 1e-6 and trans < 1e-9, (pose, rot, trans)
                assert pose_errors(c2w, other)[0] > 1.0
        assert ms.meta["pose"] == run.meta["pose"] == pose


def test_make_mirror_set():
    cams = half_ring(elev_deg=30.0)
    inputs = views_of(cams)
    scene_plane = Plane(np.zeros(3), np.array([0.0, 1.0, 0.0]))
    ms = make_mirror_set(inputs, "opposite", scene_plane, pose="lookat")
    np.testing.assert_allclose(ms.sphere.center, 0.0, atol=1e-9)
    assert ms.sphere.radius == pytest.approx(4.0)
    assert len(ms.views) == len(inputs) and len(ms.true_cameras) == len(inputs)
    for v, m, t in zip(inputs, ms.views, ms.true_cameras):
        np.testing.assert_array_equal(m.rgb, v.rgb[:, ::-1])
        np.testing.assert_array_equal(m.alpha, v.alpha[:, ::-1])
        assert m.meta["mirrored"] is True and m.meta["source"] == v.name
        assert m.name == f"{v.name}_flip"
        assert is_proper_rotation(m.camera.rotation) and is_proper_rotation(t.rotation)
        assert (m.camera.width, m.camera.height, m.camera.focal) == (v.camera.width, v.camera.height, v.camera.focal)
    errs = ms.errors_to_truth()  # 'opposite' is not the true plane y = 0 here: errors are non-zero
    assert len(errs) == 8 and all(rot > 1.0 for rot, _ in errs)
    assert ms.errors_to_truth(ms.true_cameras) == [(0.0, 0.0)] * 8
    # inputs are untouched; no true plane -> no truth; alpha may be missing
    np.testing.assert_array_equal(inputs[0].camera.c2w, cams[0].c2w)
    no_alpha = [View(v.camera, v.rgb, None, v.index) for v in inputs]
    ms2 = make_mirror_set(no_alpha, "official", None, pose="lookat")
    assert ms2.true_cameras is None and ms2.views[0].alpha is None
    np.testing.assert_allclose(ms2.plane.normal, [1.0, 0.0, 0.0])
    with pytest.raises(DatasetError):
        make_mirror_set([], "opposite", None, pose="lookat")
