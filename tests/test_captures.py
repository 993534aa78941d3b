"""Own captures: the nerfstudio and COLMAP loaders, protocol-free inputs, the drive-by export."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from flipviz.data import DatasetError, load_scene
from flipviz.data.builtin import CAMERA_ANGLE_X, render_view
from flipviz.data.cameras import Camera, look_at
from flipviz.data.capture import cameras_up
from flipviz.data.driveby import N_DRIVE, N_HELD, driveby_cameras, export_driveby
from flipviz.data.images import save_rgba_png, uncomposite
from flipviz.data.nerfstudio import load_nerfstudio
from flipviz.data.selection import select_split
from flipviz.training.config import TrainConfig

W = 64


def _ring(n: int = 6, res: int = W, focal: float | None = None) -> list[Camera]:
    f = focal if focal is not None else 0.5 * res / np.tan(0.5 * CAMERA_ANGLE_X)
    out = []
    for k in range(n):
        a = np.radians(40.0 + 25.0 * k)
        eye = np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 1.8])
        out.append(Camera(look_at(eye, np.zeros(3)), res, res, float(f), name=f"v{k}"))
    return out


# The capture's camera: fx != fy, off-centre principal point, OpenCV distortion (k1, k2, p1, p2).
FX, FY, CX, CY = 90.0, 84.0, 33.5, 30.0
DIST = (-0.18, 0.05, 0.002, -0.003)


def _distort(ideal: np.ndarray, focal: float) -> np.ndarray:
    """What the capture's camera records of a scene whose ideal pinhole image (focal, centred) is `ideal`."""
    K = np.array([[FX, 0, CX - 0.5], [0, FY, CY - 0.5], [0, 0, 1]])  # OpenCV pixel centres are integers
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(W, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], -1)[:, None]
    xy = cv2.undistortPoints(pts, K, np.array(DIST))[:, 0]  # normalised ideal coordinates
    mx = (focal * xy[:, 0] + W / 2 - 0.5).reshape(W, W).astype(np.float32)
    my = (focal * xy[:, 1] + W / 2 - 0.5).reshape(W, W).astype(np.float32)
    return cv2.remap(ideal, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))


def _write_ns(root: Path, cams: list[Camera], rgba: list[np.ndarray], doc: dict, mask_files: bool = False) -> Path:
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, (cam, im) in enumerate(zip(cams, rgba)):
        png = np.round(np.clip(im, 0, 1) * 255).astype(np.uint8)
        fr = {"file_path": f"images/{k}.png", "transform_matrix": cam.c2w.tolist()}
        if mask_files:
            (root / "masks").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "masks" / f"{k}.png"), png[..., 3])
            png[..., 3] = 255
            fr["mask_path"] = f"masks/{k}.png"
        save_rgba_png(root / fr["file_path"], png)
        frames.append(fr)
    (root / "transforms.json").write_text(json.dumps({**doc, "frames": frames}))
    return root


@pytest.fixture(scope="module")
def distorted_capture(tmp_path_factory) -> tuple[Path, list[np.ndarray]]:
    """A nerfstudio OPENCV capture of the chair (mask files), and the ideal images it should load as."""
    root = tmp_path_factory.mktemp("ns")
    focal = max(FX, FY)
    cams = _ring(focal=focal)
    ideal = []
    for c in cams:
        rgb, a = render_view("chair", c)
        ideal.append(
            np.concatenate(
                [
                    np.where(a[..., None] > 0, (rgb - 1 + a[..., None]) / np.maximum(a[..., None], 1e-6), 0),
                    a[..., None],
                ],
                -1,
            )
        )
    captured = [_distort(im.astype(np.float32), focal) for im in ideal]
    doc = {
        "camera_model": "OPENCV",
        "fl_x": FX,
        "fl_y": FY,
        "cx": CX,
        "cy": CY,
        "w": W,
        "h": W,
        "k1": DIST[0],
        "k2": DIST[1],
        "p1": DIST[2],
        "p2": DIST[3],
    }
    return _write_ns(root, cams, captured, doc, mask_files=True), ideal


def _centroid(m: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[: m.shape[0], : m.shape[1]]
    return np.array([(u * m).sum(), (v * m).sum()]) / m.sum()


def _mask_errors(scene, ideal) -> tuple[float, float]:
    """Mean silhouette centroid error (px) and worst area ratio error against the ideal masks."""
    cen = np.mean([np.linalg.norm(_centroid(v.alpha) - _centroid(ideal[k][..., 3])) for k, v in scene.views.items()])
    area = max(abs(v.alpha.sum() / ideal[k][..., 3].sum() - 1.0) for k, v in scene.views.items())
    return float(cen), float(area)


def test_nerfstudio_opencv_capture_is_undistorted_into_the_flipviz_pinhole(distorted_capture):
    root, ideal = distorted_capture
    scene = load_nerfstudio(root)
    assert not scene.protocol and scene.meta["masked"] and scene.meta["box_from"] == "masks"
    assert all(v.camera.focal == pytest.approx(max(FX, FY)) and v.alpha is not None for v in scene.views.values())
    cen, area = _mask_errors(scene, ideal)
    assert cen < 0.1 and area < 0.01, (cen, area)  # measured: 0.03-0.07 px, 0.3 %

    def read_as(**changes) -> tuple[float, float]:
        doc = json.loads((root / "transforms.json").read_text())
        try:
            (root / "transforms.json").write_text(json.dumps({**doc, **changes}))
            return _mask_errors(load_nerfstudio(root), ideal)
        finally:
            (root / "transforms.json").write_text(json.dumps(doc))

    no_dist, _ = read_as(camera_model="PINHOLE")  # the lens distortion ignored
    assert no_dist > 1.5 * cen
    ideal_cam, ideal_area = read_as(camera_model="PINHOLE", fl_x=max(FX, FY), fl_y=max(FX, FY), cx=W / 2, cy=W / 2)
    assert ideal_cam > 1.0 and ideal_area > 0.05  # measured: 2.2-2.3 px, 8 %


def test_nerfstudio_per_frame_intrinsics_rgba_and_resize(tmp_path):
    cams = _ring(4)
    rgba = [np.concatenate([rgb, a[..., None]], -1) for rgb, a in (render_view("mug", c) for c in cams)]
    doc = {"w": W, "h": W}
    root = _write_ns(tmp_path, cams, rgba, doc)
    meta = json.loads((root / "transforms.json").read_text())
    for fr in meta["frames"]:  # intrinsics per frame only
        fr.update(fl_x=cams[0].focal, fl_y=cams[0].focal, cx=W / 2, cy=W / 2)
    meta["aabb_scale"] = 2
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene("", root, res=32)
    v = scene.views[0]
    assert (v.camera.width, v.camera.height) == (32, 32) and v.camera.focal == pytest.approx(cams[0].focal / 2)
    assert v.alpha is not None and v.alpha.max() == pytest.approx(1.0)
    assert np.allclose(v.camera.c2w, cams[0].c2w)


def _one_line(fn) -> str:
    with pytest.raises(DatasetError) as e:
        fn()
    msg = str(e.value)
    assert msg and "\n" not in msg
    return msg


@pytest.mark.parametrize(
    "edit, expect",
    [
        (lambda d: d.pop("fl_x"), "missing key 'fl_x'"),
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), "not supported"),
        (
            lambda d: d["frames"][2].update(camera_model="OPENCV_FISHEYE"),
            "frame 2: camera_model OPENCV_FISHEYE is not supported",
        ),
        (
            lambda d: d["frames"][0].update(transform_matrix=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            "not a rotation",
        ),
        (lambda d: d["frames"][1].update(file_path="images/none.png"), "not found"),
        (lambda d: d.update(frames={}), "not a non-empty list"),
        (lambda d: d.update(train_filenames=["images/x.png"]), "not a frame"),
        (lambda d: d.update(applied_transform=[[1, 0]]), "applied_transform"),
        (lambda d: d.update(fl_x=-3), "bad intrinsics"),
        (lambda d: d.update(k1="a"), "malformed"),
        (lambda d: d["frames"][0].update(mask_path="masks/none.png"), "cannot read mask"),
    ],
)
def test_nerfstudio_malformed_is_one_line(distorted_capture, tmp_path, edit, expect):
    root = tmp_path / "cap"
    shutil.copytree(distorted_capture[0], root)
    doc = json.loads((root / "transforms.json").read_text())
    edit(doc)
    (root / "transforms.json").write_text(json.dumps(doc))
    assert expect in _one_line(lambda: load_nerfstudio(root))


def test_bad_json_and_unknown_folders_are_one_line(tmp_path):
    (tmp_path / "transforms.json").write_text("{nope")
    assert "not valid JSON" in _one_line(lambda: load_scene("", tmp_path))
    (tmp_path / "empty").mkdir()
    assert "holds no scene" in _one_line(lambda: load_scene("", tmp_path / "empty"))
    assert "not found" in _one_line(lambda: load_scene("", tmp_path / "missing"))


def _colmap_capture(
    root: Path, cams: list[Camera], images: list[np.ndarray], binary: bool, model: str = "PINHOLE"
) -> Path:
    import pycolmap

    rec = pycolmap.Reconstruction()
    f = cams[0].focal
    params = {
        "PINHOLE": [f, f, W / 2, W / 2],
        "SIMPLE_PINHOLE": [f, W / 2, W / 2],
        "FULL_OPENCV": [f, f, W / 2, W / 2] + [0.0] * 8,
    }[model]
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model=model, width=W, height=W, params=params))
    (root / "images").mkdir(parents=True)
    for k, (cam, im) in enumerate(zip(cams, images)):
        w2c = np.linalg.inv(cam.c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL c2w -> OpenCV w2c
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{k}.png", camera_id=1, image_id=k + 1), pycolmap.Rigid3d(w2c[:3])
        )
        save_rgba_png(root / "images" / f"{k}.png", im)
    rng = np.random.default_rng(0)
    for p in rng.uniform(-0.6, 0.6, (200, 3)):
        rec.add_point3D(p, pycolmap.Track(), np.array([200, 100, 50], np.uint8))
    out = root / "sparse" / "0"
    out.mkdir(parents=True)
    (rec.write_binary if binary else rec.write_text)(str(out))
    return root


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_text_and_binary_models(tmp_path, binary, caplog):
    cams = _ring(5)
    images = [uncomposite(*render_view("chair", c)) for c in cams]
    for im in images:
        im[..., 3] = 255  # no masks: the background is part of the capture
    root = _colmap_capture(tmp_path / "c", cams, images, binary)
    with caplog.at_level("WARNING", logger="flipviz.data"):
        scene = load_scene("", root, res=W)
    assert [r.getMessage().count("\n") for r in caplog.records] == [0] and "no masks" in caplog.text
    assert not scene.protocol and scene.meta["format"] == "colmap" and scene.meta["box_from"] == "sparse points"
    assert not scene.meta["masked"] and all(v.alpha is None for v in scene.views.values())
    for k, v in scene.views.items():
        assert np.allclose(v.camera.c2w, cams[k].c2w, atol=1e-6), (
            "COLMAP's world-to-camera (OpenCV) was not inverted to OpenGL c2w"
        )
    assert np.all(scene.bbox[0] < -0.55) and np.all(scene.bbox[1] > 0.55) and np.all(np.abs(scene.bbox) < 1.0)
    assert 0 < scene.near < 3.0 < 4.5 < scene.far
    # no masks: the inputs train on every pixel, the flipped images only on rays through the box
    from flipviz.training.setup import build_run

    ts = build_run(
        TrainConfig.from_settings(data=root, res=W, method="flip", inputs="all", mirror_plane="opposite"), scene
    ).training
    per_view = np.bincount(ts.bank.view.numpy(), minlength=len(ts.views))
    assert all(per_view[i] == W * W for i in range(len(cams)))
    assert all(0 < per_view[i] < W * W for i in ts.mirror_ids)


def test_colmap_malformed_is_one_line(tmp_path):
    cams = _ring(4)
    images = [uncomposite(*render_view("chair", c)) for c in cams]
    root = _colmap_capture(tmp_path / "c", cams, images, binary=False)
    (root / "images" / "2.png").unlink()
    assert "not found" in _one_line(lambda: load_scene("", root, res=W))
    root = _colmap_capture(tmp_path / "d", cams, images, binary=False, model="FULL_OPENCV")
    assert "not supported" in _one_line(lambda: load_scene("", root, res=W))
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE x y\n")
    assert "malformed" in _one_line(lambda: load_scene("", root, res=W))


@pytest.fixture(scope="module")
def driveby(tmp_path_factory) -> Path:
    return export_driveby("chair-turned", tmp_path_factory.mktemp("drive"), res=32)


def test_driveby_export_reads_back_as_a_capture(driveby):
    scene = load_scene("", driveby, res=32)
    assert scene.splits == {"train": list(range(N_DRIVE)), "test": list(range(N_DRIVE, N_DRIVE + N_HELD))}
    assert scene.symmetry_plane is not None and not scene.up_known
    # the robot's path: not a ring (distance and height vary), not aimed exactly at the centre
    centers = np.stack([scene.views[i].camera.center for i in scene.splits["train"]])
    r = np.linalg.norm(centers[:, :2], axis=1)
    assert r.max() - r.min() > 0.5 and np.ptp(centers[:, 2]) > 0.5
    # the box holds the object (the turned chair's bounds), from the drive-by frames' masks alone
    assert np.all(scene.bbox[0] < [-0.4, -0.8, -1.0]) and np.all(scene.bbox[1] > [0.9, 0.5, 1.0])
    up = cameras_up([c for c in driveby_cameras(32)])
    assert np.degrees(np.arccos(up @ [0, 0, 1])) < 5.0


def test_inputs_choose_frames_and_hold_out_the_rest(driveby):
    scene = load_scene("", driveby, res=32)
    split = select_split(scene, "")
    assert len(split.inputs) == N_DRIVE and len(split.tests) == N_HELD and split.uppers == [] and split.config == 0
    split = select_split(scene, "0,2,4-9")
    assert [v.index for v in split.inputs] == [0, 2, 4, 5, 6, 7, 8, 9] and len(split.tests) == N_HELD
    half = select_split(scene, "az:60..150")
    assert 4 <= len(half.inputs) < N_DRIVE
    wrap = select_split(scene, "az:150..60")  # a range that wraps through 0
    assert {v.index for v in half.inputs} | {v.index for v in wrap.inputs} == set(range(N_DRIVE + N_HELD))
    all_frames = select_split(scene, "all")
    assert len(all_frames.inputs) == N_DRIVE + N_HELD and all_frames.tests == []
    for bad in ("x", "1-", "az:1..", "99"):
        assert "--inputs" in _one_line(lambda: select_split(scene, bad))
    assert "at least 4" in _one_line(lambda: select_split(scene, "0,1"))


def test_a_driveby_capture_trains_with_its_held_out_views(driveby, tmp_path, small_torch):
    from flipviz.training.run import train

    cfg = TrainConfig.from_settings(
        data=driveby,
        res=32,
        steps=12,
        batch_rays=256,
        method="flip+u",
        mirror_plane="scene",
        out=tmp_path / "run",
        no_rrd=True,
        images_every=0,
        checkpoint_every=0,
    )
    trainer, metrics = train(cfg)
    assert metrics["status"] == "finished" and metrics["config"] == 0 and np.isfinite(metrics["psnr"])
    assert [v["name"] for v in metrics["per_view"]] == [f"frame_{i:05d}" for i in range(N_DRIVE, N_DRIVE + N_HELD)]
    assert metrics["plane"]["error_deg"] == pytest.approx(0.0, abs=1e-6)
    assert len(trainer.training.mirror_ids) == N_DRIVE
    with pytest.raises(Exception, match="Upper views"):
        train(
            TrainConfig.from_settings(data=driveby, res=32, steps=2, method="upper", out=tmp_path / "up", no_rrd=True)
        )


def test_the_app_trains_a_capture_narrower_than_its_default_at_the_captures_width(driveby, tmp_path):
    """The app's 200 px default refused a 100 px capture ("flipviz does not upscale"): the app now trains
    such data at its own width, and says so; `flipviz train` still refuses a --res wider than the data."""
    from flipviz.data import TooWide, load_scene
    from flipviz.viz.app.app import AppConfig, check_run_input

    cfg, scene = check_run_input(
        AppConfig.from_settings(data=driveby, mirror_plane="scene", out=tmp_path / "run", no_rrd=True)
    )
    assert AppConfig().data.res == 200 and cfg.data.res == 32 and scene.resolution == (32, 32)
    with pytest.raises(TooWide, match="wider than the images") as e:
        load_scene("", driveby, 64)
    assert e.value.width == 32
