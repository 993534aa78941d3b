"""The Blender / NeRF-synthetic format: reading lego, bad inputs, export and round trip."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from flipviz.data import DatasetError, export_scene, load_blender, load_builtin, load_scene, make_split, write_blender
from flipviz.data.protocol import RING_INDICES


@pytest.fixture(autouse=True)
def tmp_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FLIPVIZ_CACHE", str(tmp_path / "cache"))


def write_png(path: Path, rgba_u8: np.ndarray) -> None:
    """Write an RGB(A) uint8 array (RGB order) as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    code = cv2.COLOR_RGBA2BGRA if rgba_u8.ndim == 3 and rgba_u8.shape[2] == 4 else cv2.COLOR_RGB2BGR
    img = cv2.cvtColor(rgba_u8, code) if rgba_u8.ndim == 3 else rgba_u8
    assert cv2.imwrite(str(path), img)


def make_folder(root: Path, images: list[np.ndarray], angle: float = 0.7) -> Path:
    frames = []
    for k, img in enumerate(images):
        write_png(root / "test" / f"r_{k}.png", img)
        c2w = np.eye(4)
        c2w[:3, 3] = [0.0, 0.0, 4.0 + k]
        frames.append({"file_path": f"./test/r_{k}", "transform_matrix": c2w.tolist()})
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return root


def rgba(h: int, w: int, color=(255, 0, 0, 255)) -> np.ndarray:
    return np.tile(np.uint8(color), (h, w, 1))


def test_reads_rgba_in_rgb_order_on_white(tmp_path):
    img = rgba(4, 6, (255, 0, 0, 255))
    img[0, 0] = (0, 0, 255, 0)  # transparent blue: white after compositing
    img[1, 1] = (0, 255, 0, 51)  # 20 % green over white
    scene = load_blender(make_folder(tmp_path / "s", [img, img]))
    v = scene.views[1]
    assert v.rgb.shape == (4, 6, 3) and v.rgb.dtype == np.float32 and v.alpha.shape == (4, 6)
    assert np.allclose(v.rgb[2, 2], [1, 0, 0]) and v.alpha[2, 2] == 1.0
    assert np.allclose(v.rgb[0, 0], [1, 1, 1]) and v.alpha[0, 0] == 0.0
    assert np.allclose(v.rgb[1, 1], [0.8, 1.0, 0.8], atol=1e-6)
    assert np.isclose(v.camera.focal, 0.5 * 6 / np.tan(0.35)) and v.index == 1 and v.name == "r_1"
    assert np.allclose(v.camera.center, [0, 0, 5])
    assert scene.near == 2.0 and scene.far == 6.0 and scene.symmetry_plane is None
    assert np.allclose(scene.bbox, [[-1.5] * 3, [1.5] * 3])
    rgb_only = load_blender(make_folder(tmp_path / "rgb", [rgba(4, 6, (0, 0, 255, 255))[..., :3]]))
    assert np.allclose(rgb_only.views[0].rgb, [0, 0, 1]) and np.all(rgb_only.views[0].alpha == 1)


def test_downscale_is_alpha_premultiplied(tmp_path):
    img = rgba(2, 2, (0, 255, 0, 0))  # invisible green must not bleed in
    img[0, 0] = (255, 0, 0, 255)
    v = load_blender(make_folder(tmp_path / "s", [img]), res=1).views[0]
    assert v.rgb.shape == (1, 1, 3)
    assert np.isclose(v.alpha[0, 0], 0.25)
    assert np.allclose(v.rgb[0, 0], [1.0, 0.75, 0.75], atol=1e-6)  # 0.25 red + 0.75 white
    assert np.isclose(v.camera.focal, 0.5 * 1 / np.tan(0.35))


def one_line_error(fn) -> str:
    with pytest.raises(DatasetError) as e:
        fn()
    msg = str(e.value)
    assert msg and "\n" not in msg
    return msg


def test_bad_inputs_raise_one_line_errors(tmp_path):
    good = [rgba(4, 4), rgba(4, 4)]
    assert "not found" in one_line_error(lambda: load_blender(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    assert "transforms_test.json not found" in one_line_error(lambda: load_blender(tmp_path / "empty"))

    bad_json = make_folder(tmp_path / "badjson", good)
    (bad_json / "transforms_test.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    assert "not valid JSON" in one_line_error(lambda: load_blender(bad_json))

    no_angle = make_folder(tmp_path / "noangle", good)
    (no_angle / "transforms_test.json").write_text(json.dumps({"frames": []}))
    assert "camera_angle_x" in one_line_error(lambda: load_blender(no_angle))

    no_matrix = make_folder(tmp_path / "nomatrix", good)
    doc = json.loads((no_matrix / "transforms_test.json").read_text())
    del doc["frames"][1]["transform_matrix"]
    (no_matrix / "transforms_test.json").write_text(json.dumps(doc))
    assert "transform_matrix" in one_line_error(lambda: load_blender(no_matrix))

    bad_matrix = make_folder(tmp_path / "badmatrix", good)
    doc["frames"][1]["transform_matrix"] = [[1, 0], [0, 1]]
    (bad_matrix / "transforms_test.json").write_text(json.dumps(doc))
    assert "4x4" in one_line_error(lambda: load_blender(bad_matrix))

    no_frames = make_folder(tmp_path / "noframes", good)
    (no_frames / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert "malformed" in one_line_error(lambda: load_blender(no_frames))

    missing = make_folder(tmp_path / "missing", good)
    (missing / "test" / "r_1.png").unlink()
    assert "r_1.png" in one_line_error(lambda: load_blender(missing))

    sizes = make_folder(tmp_path / "sizes", [rgba(4, 4), rgba(4, 5)])
    assert "inconsistent sizes" in one_line_error(lambda: load_blender(sizes))

    gray = make_folder(tmp_path / "gray", [np.full((4, 4), 128, np.uint8)])
    assert "RGB" in one_line_error(lambda: load_blender(gray))

    not_png = make_folder(tmp_path / "notpng", good)
    (not_png / "test" / "r_0.png").write_bytes(b"garbage")
    assert "cannot read" in one_line_error(lambda: load_blender(not_png))

    assert "transforms_train.json" in one_line_error(
        lambda: load_blender(make_folder(tmp_path / "split", good), "train")
    )


def test_write_load_round_trip(tmp_path):
    scene = load_builtin("chair", res=24)  # the protocol's 32 views: not contiguous orbit indices
    out = write_blender(scene, tmp_path / "chair")
    back = load_blender(out)
    assert sorted(back.views) == sorted(scene.views)
    for i, v in scene.views.items():
        w = back.views[i]
        assert np.allclose(w.camera.c2w, v.camera.c2w, atol=1e-12)
        assert np.isclose(w.camera.focal, v.camera.focal) and (w.camera.width, w.camera.height) == (24, 24)
        assert np.abs(w.alpha - v.alpha).max() <= 0.5 / 255 + 1e-6  # 8-bit PNG quantisation
        assert np.abs(w.rgb - v.rgb).max() <= 1.0 / 255 + 1e-6
    assert make_split(back, 5).config == 5


def test_export_scene_full_turn(tmp_path):
    out = export_scene("truck", tmp_path / "truck", res=16)
    doc = json.loads((out / "transforms_test.json").read_text())
    assert len(doc["frames"]) == 100 and "orbit_index" not in doc["frames"][0]  # frame order = orbit index
    back = load_scene("ignored", out, res=16)
    ref = load_builtin("truck", res=16)
    assert sorted(back.views) == list(range(100))
    for i in ref.views:
        assert np.allclose(back.views[i].camera.c2w, ref.views[i].camera.c2w)
        assert np.abs(back.views[i].rgb - ref.views[i].rgb).max() <= 1.0 / 255 + 1e-6


def test_lego(lego_dir: Path):
    scene = load_blender(lego_dir)
    assert len(scene.views) == 200 and scene.resolution == (200, 200)
    v = scene.views[0]
    assert v.rgb.dtype == np.float32 and 0.0 <= v.rgb.min() and v.rgb.max() <= 1.0
    assert v.rgb.shape == (200, 200, 3) and 0.05 < v.alpha.mean() < 0.9
    assert np.all(v.rgb[v.alpha == 0] == 1.0)  # white background
    assert np.isclose(v.camera.focal, 0.5 * 200 / np.tan(0.5 * 0.6911112070083618))
    assert np.isclose(np.linalg.norm(v.camera.center), 4.031, atol=1e-3)
    split = make_split(scene, 1)
    assert [w.index for w in split.inputs] == list(RING_INDICES[:8])
    assert [w.index for w in split.uppers] == [i + 1 for i in RING_INDICES[8:]]
    assert all(w.rgb.shape == (200, 200, 3) for w in split.inputs + split.tests + split.uppers)
    # downscaled load = area average of the composited full-resolution image
    small = load_blender(lego_dir, res=50, indices=[0, 1])
    assert sorted(small.views) == [0, 1] and small.resolution == (50, 50)
    ref = v.rgb.reshape(50, 4, 50, 4, 3).mean(axis=(1, 3))
    assert np.abs(small.views[0].rgb - ref).max() < 1e-5
