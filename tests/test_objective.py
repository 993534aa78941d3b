"""The training objective of Sec. IV-C and the beta^2 it learns from (model/objective.py, renderer.py).

Each test names the behaviour it guards; `studies/check_mutations.py` breaks each on purpose
and checks that this suite fails.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from flipviz.model import GridConfig, ModelConfig, NerfConfig, Objective, RadianceModel
from flipviz.model.renderer import render_rays
from flipviz.training import flip
from flipviz.training.config import TrainConfig

B_MIN = 0.1
W = 0.01


def batch():
    """Three rays: two uncertain, one certain, with known errors, variances and densities."""
    rgb = torch.tensor([[0.2, 0.4, 0.6], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]], requires_grad=True)
    target = torch.tensor([[0.3, 0.4, 0.2], [0.5, 1.0, 1.0], [0.1, 0.5, 0.7]])
    out = {
        "rgb": rgb,
        "beta2": torch.tensor([0.04, 0.5, B_MIN**2], requires_grad=True),
        "sigma_mean": torch.tensor([2.0, 0.0, 3.0], requires_grad=True),
    }
    return out, target, torch.tensor([True, True, False])


def by_hand() -> float:
    """Eqn. 7 for the uncertain rays, ||.||^2 / (2 beta_min^2) for the certain one, mean, times 2 b^2 / 3."""
    sq = [0.01 + 0.0 + 0.16, 0.25, 0.16 + 0.0 + 0.04]
    r0 = sq[0] / (2 * 0.04) + math.log(0.04) / 2 + W * 2.0
    r1 = sq[1] / (2 * 0.5) + math.log(0.5) / 2 + W * 0.0
    r2 = sq[2] / (2 * B_MIN**2)
    return (2 * B_MIN**2 / 3) * (r0 + r1 + r2) / 3


def test_the_nll_applies_to_uncertain_rays_after_the_warm_up():
    out, target, unc = batch()
    got = Objective(B_MIN, W, nll_start=5)(out, target, unc, step=5)
    assert got.item() == pytest.approx(by_hand(), rel=1e-6)


def test_certain_rays_contribute_exactly_their_mse():
    """Under the NLL a certain ray's loss and gradient are those of the per-channel MSE."""
    out, target, unc = batch()
    obj = Objective(B_MIN, W, nll_start=0)
    obj(out, target, unc, step=0).backward()
    g_nll = out["rgb"].grad[2].clone()
    out2 = {k: v.detach().clone().requires_grad_(True) for k, v in out.items()}
    ((out2["rgb"] - target) ** 2).sum(-1).div(3.0).mean().backward()  # the MSE of the same batch
    assert torch.allclose(g_nll, out2["rgb"].grad[2], atol=1e-7)
    # a batch of certain rays only: the MSE, before and after the warm-up
    none = torch.zeros(3, dtype=torch.bool)
    mse = ((out["rgb"] - target) ** 2).mean().item()
    assert obj(out, target, none, step=0).item() == pytest.approx(mse, rel=1e-6)


def test_warm_up_boundary_from_the_run_config():
    """Flip's objective: plain MSE for the first uncertainty_start of the steps, the NLL from then on."""
    cfg = TrainConfig.from_settings(steps=100, uncertainty_start=0.2, density_weight=W)
    obj = flip.objective(cfg.flip, cfg.engine.steps, B_MIN)
    assert obj.nll_start == 20
    out, target, unc = batch()
    mse = ((out["rgb"] - target) ** 2).mean().item()
    assert obj(out, target, unc, step=19).item() == pytest.approx(mse, rel=1e-6)
    assert obj(out, target, unc, step=20).item() == pytest.approx(by_hand(), rel=1e-6)


def test_density_regulariser_value_and_weight_from_the_config():
    """d L / d sigma_mean = (2 beta_min^2 / 3) w / R on uncertain rays, 0 on certain ones."""
    cfg = TrainConfig.from_settings(steps=10, uncertainty_start=0.0, density_weight=0.05)
    obj = flip.objective(cfg.flip, cfg.engine.steps, B_MIN)
    out, target, unc = batch()
    obj(out, target, unc, step=0).backward()
    per_ray = (2 * B_MIN**2 / 3) * 0.05 / 3
    assert out["sigma_mean"].grad.tolist() == pytest.approx([per_ray, per_ray, 0.0], rel=1e-6)


class Slab:
    """A test field: density s inside |z| < 0.5, nothing elsewhere; colour 0.5, beta raw r everywhere."""

    with_beta = True

    def __init__(self, s: float, v: float):
        self.s = s
        self.raw = torch.tensor(math.log(math.expm1(v)), requires_grad=True)  # softplus(raw) = v

    def query(self, x, d):
        sigma = torch.where(x[..., 2].abs() < 0.5, self.s, 0.0)
        return sigma, lambda w, rows: (
            torch.arange(w.numel()),
            torch.full((w.numel(), 3), 0.5),
            self.raw.expand(w.numel()),
        )


@pytest.mark.parametrize("mode, sum_wp", [("linear", 0.75), ("variance", 0.3125)])
def test_beta2_compositing_on_a_slab_with_known_weights(mode, sum_wp):
    """Four samples at z = 0.75, 0.25, -0.25, -0.75 (delta 0.5); s = 2 ln 2 gives alpha = 1/2 in the
    slab, so w = (0, 1/2, 1/4, 0): sum w = 3/4 (linear, as the official code) and sum w^2 = 5/16."""
    field, v = Slab(2 * math.log(2.0), 0.2), 0.2
    o, d = torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    bbox = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    out = render_rays(
        field, o, d, bbox=bbox, near=0.5, far=6.0, n_samples=4, training=False, beta_min=B_MIN, beta2_mode=mode
    )
    assert out["opacity"].item() == pytest.approx(0.75, rel=1e-6)
    assert out["beta2"].item() == pytest.approx(B_MIN**2 + v * sum_wp, rel=1e-6)
    assert out["rgb"][0].tolist() == pytest.approx([0.75 * 0.5 + 0.25] * 3, rel=1e-6)


@pytest.mark.parametrize(
    "field", [GridConfig(grid_res=(16,), upsample_at=()), NerfConfig(depth=2, width=32, pe=4, dir_pe=2)]
)
def test_the_beta_head_learns(field):
    """The NLL's gradient reaches the variance head through the rendered beta^2 (nothing detached)."""
    torch.manual_seed(0)
    m = RadianceModel(ModelConfig(field, n_samples=32), np.array([[-1.0] * 3, [1.0] * 3]), 0.5, 6.0, with_beta=True)
    if isinstance(field, GridConfig):
        with torch.no_grad():
            m.field.density_grid.fill_(3.0)  # opaque enough that samples get colour (and beta)
    g = torch.Generator().manual_seed(0)
    o = torch.randn(256, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = -o / o.norm(dim=-1, keepdim=True)
    out = m.render_rays(o, d, training=True)
    Objective(B_MIN, W, nll_start=0)(out, torch.zeros(256, 3), torch.ones(256, dtype=torch.bool), step=0).backward()
    head = m.field.rgbnet[-1] if isinstance(field, GridConfig) else m.field.out
    assert head.bias.grad[3].abs().item() > 1e-6
    assert head.weight.grad[3].abs().sum().item() > 1e-6
