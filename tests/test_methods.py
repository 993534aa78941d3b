"""The five methods: which views, flags and refined poses each one trains with."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flipviz.data.protocol import make_split
from flipviz.errors import UserError
from flipviz.training import flip
from flipviz.training.config import METHODS, TrainConfig
from flipviz.training.methods import build_training_set, method_spec

RES = 24


@pytest.fixture(scope="module")
def chair():
    from flipviz.data.builtin import load_builtin

    return load_builtin("chair", RES)


def _ts(scene, **kw):
    cfg = TrainConfig.from_settings(res=RES, **kw)
    spec = method_spec(cfg)
    split = make_split(scene, cfg.data.config)
    mirrors = flip.mirrored_train_views(spec, flip.mirrored_views(cfg.flip, split.inputs, scene), scene.bbox)
    return build_training_set(spec, split.inputs, mirrors, split.uppers)


@pytest.mark.parametrize(
    "method, n_views, n_refined, unc_kinds",
    [
        ("bl", 8, 0, set()),
        ("bl+u", 8, 0, {"input"}),
        ("flip", 16, 8, set()),
        ("flip+u", 16, 8, {"mirror"}),
        ("upper", 16, 0, set()),
    ],
)
def test_training_sets(chair, method, n_views, n_refined, unc_kinds):
    ts = _ts(chair, method=method)
    assert len(ts.views) == n_views
    assert int(ts.refine_mask.sum()) == n_refined
    assert {v.kind for v in ts.views if v.uncertain} == unc_kinds
    assert all(v.kind == "mirror" for v in ts.views if v.refine)
    b = ts.bank
    assert len(b) == n_views * RES * RES
    assert b.dirs_cam.shape == (len(b), 3) and b.rgb.shape == (len(b), 3)
    # per-view flags agree with the views; each ray points at its view
    assert ts.uncertain.tolist() == [v.uncertain for v in ts.views]
    assert ts.refine_mask.tolist() == [v.refine for v in ts.views]
    cam = b.view.numpy()
    assert np.array_equal(np.bincount(cam), np.full(n_views, RES * RES))
    # targets are the views' images, row-major
    v0 = ts.views[-1]
    assert torch.equal(b.rgb[cam == len(ts.views) - 1], torch.from_numpy(v0.image.reshape(-1, 3)))
    assert method_spec(TrainConfig.from_settings(method=method)).uses_beta == bool(unc_kinds)


def test_ablation_switches(chair):
    ts = _ts(chair, method="flip+u", ba=False)
    assert not bool(ts.refine_mask.any()) and any(v.uncertain for v in ts.views)
    ts = _ts(chair, method="flip+u", uncertainty=False)
    assert int(ts.refine_mask.sum()) == 8 and not any(v.uncertain for v in ts.views)
    ts = _ts(chair, method="flip", refine="all")
    assert int(ts.refine_mask.sum()) == 16
    # mirrored views are the flipped inputs
    inputs = [v for v in ts.views if v.kind == "input"]
    mirrors = [v for v in ts.views if v.kind == "mirror"]
    assert np.array_equal(mirrors[0].image, inputs[0].image[:, ::-1])


def test_unknown_method():
    with pytest.raises(UserError, match="unknown method"):
        method_spec(TrainConfig.from_settings(method="nope"))
    assert set(METHODS) == {"bl", "bl+u", "flip", "flip+u", "upper"}


@pytest.mark.parametrize("refine", ["mirrored", "all"])
def test_original_poses_fixed_unless_refine_all(chair, tmp_path, refine):
    from flipviz.training.trainer import Trainer

    cfg = TrainConfig.from_settings(
        method="flip",
        refine=refine,
        res=RES,
        steps=15,
        batch_rays=512,
        n_samples=32,
        grid_res=(32,),
        out=tmp_path / "run",
        images_every=0,
        checkpoint_every=0,
        eval_on_stop=False,
        mirror_plane="official",
    )
    tr = Trainer(cfg, scene=chair)
    for _ in range(cfg.engine.steps):
        tr._train_step()
    with torch.no_grad():
        now = tr.flip.poses()
    init = tr.training.init_c2w
    is_input = torch.tensor([v.kind == "input" for v in tr.training.views])
    moved = (now - init).abs().flatten(1).amax(1)
    assert (~is_input).sum() == 8 and bool((moved[~is_input] > 1e-6).all()), "mirrored poses must move under BA"
    if refine == "mirrored":
        assert float(moved[is_input].max()) == 0.0
    else:
        assert bool((moved[is_input] > 1e-6).all())
