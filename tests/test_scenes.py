"""Built-in scenes: exact geometric symmetry, the ray-cast renderer, the orbit and the cache."""

import os

import numpy as np
import pytest

from flipviz.data import (
    SCENES,
    Camera,
    DatasetError,
    build_mesh,
    load_builtin,
    orbit_camera,
    render_view,
    symmetry_plane,
)
from flipviz.data.builtin import _cache_path
from flipviz.data.cameras import look_at
from flipviz.data.protocol import protocol_indices
from flipviz.data.raycast import LIGHT_DIR, render_mesh
from flipviz.data.scenes import BASE_SCENES, TURN_OFFSET
from flipviz.geometry.mirror import exact_reflected_camera

RES = 32


@pytest.fixture(autouse=True)
def tmp_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FLIPVIZ_CACHE", str(tmp_path / "cache"))


def reflect_matrix(normal) -> np.ndarray:
    """Householder reflection through the plane through the origin with this normal."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    return np.eye(3) - 2.0 * np.outer(n, n)


def triangle_set(vertices: np.ndarray, faces: np.ndarray) -> set:
    tris = vertices[faces]  # (F, 3, 3); a triangle as the sorted tuple of its corners
    return {tuple(sorted(map(tuple, t))) for t in np.round(tris, 12) + 0.0}  # + 0.0: -0.0 -> 0.0


def is_mirror_symmetric(mesh, normal) -> bool:
    v = np.asarray(mesh.vertices)
    return triangle_set(v, mesh.faces) == triangle_set(v @ reflect_matrix(normal).T, mesh.faces)


def mirrored_camera(cam: Camera, normal) -> Camera:
    """Reflect the camera through the plane, then negate its x axis (a proper camera whose image is
    the horizontal flip of what the reflected, improper camera sees)."""
    S = reflect_matrix(normal)
    c2w = np.eye(4)
    c2w[:3, :3] = S @ cam.rotation @ np.diag([-1.0, 1.0, 1.0])
    c2w[:3, 3] = S @ cam.center
    return cam.with_pose(c2w)


def test_scene_registry():
    assert len(SCENES) >= 4
    assert sum(s.symmetric for s in SCENES.values()) >= 2
    assert {"chair", "mug", "lamp"} <= set(SCENES)
    assert symmetry_plane("mug") is None and symmetry_plane("lamp") is None
    with pytest.raises(DatasetError, match="available: chair") as e:
        build_mesh("sofa")
    assert "\n" not in str(e.value)
    with pytest.raises(DatasetError):
        load_builtin("sofa", res=RES)


@pytest.mark.parametrize("name", list(SCENES))
def test_meshes_fit_the_nerf_box(name):
    """Inside [-1.2, 1.2]^3 and roughly centred; the turned scenes are moved off the origin on
    purpose (by TURN_OFFSET), and their yawed boxes reach 1.3 (the truck's length)."""
    m = build_mesh(name)
    turned = name.endswith("-turned")
    assert np.abs(m.bounds).max() <= (1.35 if turned else 1.2)
    assert len(m.visual.face_colors) == len(m.faces)
    centre = m.bounds.mean(axis=0) - (np.array(TURN_OFFSET) if turned else 0.0)
    assert np.abs(centre).max() < 0.3


@pytest.mark.parametrize("name", [n for n, s in BASE_SCENES.items() if s.symmetric])  # turned: test_plane_estimate.py
def test_symmetric_geometry_is_exact_but_colours_are_not(name):
    m, plane = build_mesh(name), symmetry_plane(name)
    assert np.allclose(plane.point, 0)
    assert is_mirror_symmetric(m, plane.normal)
    # colours differ somewhere between a face and its mirror image
    S = reflect_matrix(plane.normal)
    key = lambda t: tuple(sorted(map(tuple, np.round(t, 12) + 0.0)))  # noqa: E731
    v = np.asarray(m.vertices)
    color = {key(v[f]): tuple(c[:3]) for f, c in zip(m.faces, m.visual.face_colors)}
    assert any(color[key(v[f] @ S.T)] != color[key(v[f])] for f in m.faces)


@pytest.mark.parametrize("name", [n for n, s in BASE_SCENES.items() if not s.symmetric])
def test_asymmetric_scenes_are_not_symmetric(name):
    m = build_mesh(name)
    for angle in np.radians(np.arange(0, 180, 15)):  # vertical planes through the z axis
        assert not is_mirror_symmetric(m, [np.cos(angle), np.sin(angle), 0.0])
    # and no view of the orbit equals the flip of its mirrored view about the x = 0 plane
    cam = orbit_camera(12, RES)
    _, a = render_view(name, cam)
    _, b = render_view(name, mirrored_camera(cam, [1.0, 0.0, 0.0]))
    assert np.abs(a - b[:, ::-1]).mean() > 0.01


def test_render_is_deterministic_and_shaped():
    cam = orbit_camera(25, RES)
    rgb, alpha = render_view("chair", cam)
    rgb2, alpha2 = render_view("chair", cam)
    assert np.array_equal(rgb, rgb2) and np.array_equal(alpha, alpha2)
    assert rgb.shape == (RES, RES, 3) and alpha.shape == (RES, RES)
    assert rgb.dtype == np.float32 and alpha.dtype == np.float32
    assert 0 <= rgb.min() and rgb.max() <= 1 and 0 <= alpha.min() and alpha.max() <= 1
    # background is white, the object covers a sensible part of the image
    assert np.all(rgb[alpha == 0] == 1.0)
    assert 0.05 < alpha.mean() < 0.6
    # any resolution and aspect ratio
    wide = Camera(cam.c2w, 40, 24, cam.focal * 40 / RES)
    rgb, alpha = render_view("chair", wide)
    assert rgb.shape == (24, 40, 3) and alpha.shape == (24, 40)


def test_supersampling_antialiases():
    cam = orbit_camera(6, RES)
    _, alpha = render_mesh(build_mesh("truck"), cam)
    assert np.any((alpha > 0) & (alpha < 1))  # fractional coverage at the edges
    assert set(np.unique(alpha)) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    _, hard = render_mesh(build_mesh("truck"), cam, supersample=1)
    assert set(np.unique(hard)) <= {0.0, 1.0}


@pytest.mark.parametrize("name", [n for n, s in BASE_SCENES.items() if s.symmetric])  # turned: the same objects
def test_mirror_identity_of_symmetric_scene(name):
    """Symmetric geometry, uniform albedo and a reflected light: the mirrored camera's image,
    flipped, is the original image (to within rare Embree edge ties)."""
    m, plane = build_mesh(name), symmetry_plane(name)
    m.visual.face_colors = np.tile(np.uint8([180, 120, 60, 255]), (len(m.faces), 1))
    S = reflect_matrix(plane.normal)
    cam = orbit_camera(12, RES)
    rgb, alpha = render_mesh(m, cam)
    rgb_m, alpha_m = render_mesh(m, exact_reflected_camera(cam, plane), light_dir=S @ LIGHT_DIR)
    assert np.mean(np.abs(alpha - alpha_m[:, ::-1]) > 1e-6) < 0.005
    assert np.mean(np.abs(rgb - rgb_m[:, ::-1]).max(-1) > 1e-5) < 0.005
    # with the real colours and the fixed light the flip is NOT a true view (the paper's point)
    rgb_c, _ = render_view(name, cam)
    rgb_cm, _ = render_view(name, exact_reflected_camera(cam, plane))
    assert np.abs(rgb_c - rgb_cm[:, ::-1]).mean() > 0.005


def test_orbit_cameras():
    for i in (0, 1, 25, 50, 99):
        cam = orbit_camera(i, RES)
        c = cam.center
        assert np.isclose(np.linalg.norm(c), 4.0)
        assert np.isclose(np.degrees(np.arcsin(c[2] / 4.0)), 30.0)
        assert np.isclose(np.degrees(np.arctan2(c[1], c[0])) % 360, (90 + 3.6 * i) % 360)
        R = cam.rotation
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(-R[:, 2], -c / 4.0)  # looks at the origin
        assert R[2, 1] > 0  # image up points up
    # focal from lego's camera_angle_x: 0.5 W / tan(0.5 angle)
    assert np.isclose(orbit_camera(0, 200).focal, 277.7777578)
    assert np.allclose(look_at(np.array([0.0, 4.0, 0.0]), np.zeros(3))[:3, 0], [-1.0, 0.0, 0.0])


def test_load_builtin_and_cache(tmp_path):
    scene = load_builtin("lamp", res=RES)
    assert sorted(scene.views) == protocol_indices()
    assert scene.resolution == (RES, RES) and scene.near == 2.0 and scene.far == 6.0
    assert scene.symmetry_plane is None and load_builtin("chair", res=16).symmetry_plane is not None
    bounds = build_mesh("lamp").bounds
    assert np.all(scene.bbox[0] < bounds[0]) and np.all(scene.bbox[1] > bounds[1])
    v = scene.views[19]
    assert v.index == 19 and v.name == "r_19"
    rgb, alpha = render_view("lamp", v.camera)
    assert np.array_equal(rgb, v.rgb) and np.array_equal(alpha, v.alpha)

    path = _cache_path("lamp", RES)
    assert path.is_file() and str(path).startswith(str(tmp_path))
    mtime = os.stat(path).st_mtime_ns
    again = load_builtin("lamp", res=RES)  # a cache hit: no re-render, no re-write
    assert os.stat(path).st_mtime_ns == mtime
    assert all(np.array_equal(again.views[i].rgb, scene.views[i].rgb) for i in scene.views)
    assert not list(path.parent.glob("*.tmp*"))  # atomic writes leave nothing behind
    fresh = load_builtin("lamp", res=RES, cache=False)
    assert all(np.array_equal(fresh.views[i].alpha, scene.views[i].alpha) for i in scene.views)

    path.write_bytes(b"not an npz")  # a corrupt cache is re-rendered
    healed = load_builtin("lamp", res=RES)
    assert np.array_equal(healed.views[0].rgb, scene.views[0].rgb)
    extra = load_builtin("lamp", res=RES, indices=[3, 0])
    assert sorted(extra.views) == [0, 3]
    assert np.array_equal(extra.views[0].rgb, scene.views[0].rgb)
    with pytest.raises(DatasetError, match="resolution"):
        load_builtin("lamp", res=0)
