"""Model layer: rendering maths, fitting, checkpoints, both fields (the objective: test_objective.py)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from flipviz.data.cameras import rays_from_c2w
from flipviz.data.rays import RayBank
from flipviz.model import GridConfig, ModelConfig, NerfConfig, Objective, RadianceModel
from flipviz.model.fit import fit, image_psnr
from flipviz.model.renderer import render_rays

BBOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SMALL_GRID = dict(grid_res=(16, 24), upsample_at=(0.5,), occ_start=5, occ_every=5, tv_samples=1024)
SMALL_NERF = dict(depth=2, width=32, pe=4, dir_pe=2, lr=5e-3)


pytestmark = pytest.mark.usefixtures("small_torch")


@pytest.fixture(scope="module")
def chair32():
    from flipviz.data.builtin import load_builtin
    from flipviz.data.protocol import RING_INDICES

    return load_builtin("chair", res=32, indices=RING_INDICES)


def random_rays(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from a sphere of radius 3 roughly towards the origin (some miss the box)."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = -o + 1.5 * torch.randn(n, 3, generator=g)
    return o, d / d.norm(dim=-1, keepdim=True)


def small_config(kind: str, n_samples: int | None = None, **field_kw) -> ModelConfig:
    if kind == "grid":
        return ModelConfig(GridConfig(**{**SMALL_GRID, **field_kw}), n_samples=n_samples or 32)
    return ModelConfig(NerfConfig(**{**SMALL_NERF, **field_kw}), n_samples=n_samples or 16)


def make(kind: str, with_beta: bool = True, beta2_mode: str = "linear", beta_min: float = 0.1, **kw) -> RadianceModel:
    cfg = small_config(kind, **kw)
    cfg.beta2_mode, cfg.beta_min = beta2_mode, beta_min
    return RadianceModel(cfg, BBOX, 0.5, 6.0, with_beta, "cpu")


def bump_density(model: RadianceModel) -> None:
    """Make the grid visibly non-empty (a solid core) so that weights are not all tiny."""
    with torch.no_grad():
        g = model.field.density_grid  # (Z, Y, X, 1)
        Z, Y, X = g.shape[:3]
        g[Z // 4 : 3 * Z // 4, Y // 4 : 3 * Y // 4, X // 4 : 3 * X // 4] = 20.0
        g.add_(torch.randn_like(g))
        model.field.rgbnet[-1].bias.add_(torch.randn(4))


@pytest.mark.parametrize("kind", ["grid", "nerf"])
@pytest.mark.parametrize("mode", ["linear", "variance"])
def test_beta2_at_least_beta_min_squared(kind, mode):
    m = make(kind, beta2_mode=mode, beta_min=0.05)
    if kind == "grid":
        bump_density(m)
    o, d = random_rays(2000)
    out = m.render_rays(o, d, training=False)
    b2 = out["beta2"]
    assert b2.shape == (2000,)
    assert torch.all(b2 >= 0.05**2 - 1e-9)
    # rays that miss the box have exactly beta_min^2, opacity 0, white colour
    assert torch.all(out["opacity"] >= 0) and torch.all(out["opacity"] <= 1 + 1e-5)
    miss = out["opacity"] == 0
    assert miss.any() and (~miss).any()
    assert torch.allclose(b2[miss], torch.full_like(b2[miss], 0.05**2))
    assert torch.allclose(out["rgb"][miss], torch.ones_like(out["rgb"][miss]))
    # on hit rays beta2 really exceeds beta_min^2 (the head contributes)
    assert (b2[~miss] > 0.05**2 + 1e-6).any()


def test_variance_mode_below_linear_mode():
    """sum w^2 b <= sum w b for weights in [0, 1]: the two modes differ, in the right order."""
    lin = make("grid", beta2_mode="linear")
    bump_density(lin)
    var = make("grid", beta2_mode="variance")
    var.load_state_dict(lin.state_dict())
    o, d = random_rays(500)
    b_lin = lin.render_rays(o, d, training=False)["beta2"]
    b_var = var.render_rays(o, d, training=False)["beta2"]
    assert torch.all(b_var <= b_lin + 1e-7)
    assert (b_var < b_lin - 1e-6).any()


def test_rendering_matches_quadrature_for_a_constant_density_slab():
    """A ray through a box of constant density s: opacity = 1 - exp(-s * length) (Eqn. 1)."""
    m = make("grid", with_beta=False, n_samples=64, grid_res=(16,), upsample_at=())
    f = m.field
    target_sigma = 1.5
    with torch.no_grad():  # softplus(raw + shift) / voxel0 = target_sigma
        raw = np.log(np.expm1(target_sigma * f.voxel0)) - f.shift
        f.density_grid.fill_(raw)
    o = torch.tensor([[0.0, 0.0, 3.0], [0.3, -0.2, 3.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    with torch.no_grad():
        out = m.render_rays(o, d, training=False)
    expect = 1 - np.exp(-target_sigma * 2.0)
    assert np.allclose(out["opacity"].numpy(), expect, atol=1e-4)
    assert np.allclose(out["sigma_mean"].numpy(), target_sigma, rtol=1e-4)


@pytest.mark.parametrize("kind", ["grid", "nerf"])
def test_interface_and_gradients(kind):
    """Every parameter the optimiser holds (grids, colour MLP with its beta head; the whole NeRF)
    gets a finite, non-zero gradient from the uncertainty objective, and one step changes it."""
    m = make(kind)
    if kind == "grid":
        bump_density(m)
    opt = m.make_optimizer()
    assert m.update_schedule(0, 10) is False
    o, d = random_rays(256)
    out = m.render_rays(o, d, training=True)
    assert set(out) == {"rgb", "depth", "opacity", "sigma_mean", "beta2"}
    assert out["rgb"].shape == (256, 3) and out["depth"].shape == (256,)
    uncertain = torch.ones(256, dtype=torch.bool)
    loss = Objective(nll_start=0)(out, torch.full((256, 3), 0.5), uncertain, step=0) + m.regulariser()
    opt.zero_grad()
    loss.backward()
    params = {g["name"]: g["params"] for g in opt.param_groups}
    assert set(params) == ({"density", "feat", "mlp"} if kind == "grid" else {"mlp"})
    before = {}
    for name, ps in params.items():
        for i, p in enumerate(ps):
            assert p.grad is not None and torch.isfinite(p.grad).all(), (name, i)
            assert p.grad.abs().sum() > 0, (name, i, tuple(p.shape))
            before[(name, i)] = p.detach().clone()
    opt.step()
    assert all(not torch.equal(p, before[(n, i)]) for n, ps in params.items() for i, p in enumerate(ps))
    m2 = make(kind, with_beta=False)
    assert "beta2" not in m2.render_rays(o, d, training=False)


def test_bad_config_raises():
    with pytest.raises(ValueError):
        GridConfig(grid_res=(16, 32), upsample_at=())
    with pytest.raises(ValueError):
        RadianceModel(ModelConfig(), np.array([[1.0, 1, 1], [0, 0, 0]]), 0.5, 6.0, False)
    with pytest.raises(ValueError):
        make("grid", beta2_mode="sum").render_rays(*random_rays(4), training=False)


def ring(scene):
    from flipviz.data.protocol import RING_INDICES

    return [scene.views[i] for i in RING_INDICES]


@pytest.mark.parametrize("kind", ["grid", "nerf"])
@pytest.mark.slow
def test_fit_reduces_loss_and_checkpoint_round_trip(kind, chair32):
    views = ring(chair32)
    if kind == "grid":
        cfg = ModelConfig(GridConfig(grid_res=(24, 40), upsample_at=(0.5,), occ_start=30, occ_every=10), n_samples=48)
    else:
        cfg = small_config("nerf")
    m = RadianceModel(cfg, chair32.bbox, chair32.near, chair32.far, True)
    before = image_psnr(m, views[:2])
    res0 = m.field.resolution if kind == "grid" else None
    fit(m, views, steps=80 if kind == "grid" else 60, batch_rays=1024)
    after = image_psnr(m, views[:2])
    assert after > before + (3.0 if kind == "grid" else 1.0), (before, after)  # the tiny MLP is slower
    if kind == "grid":
        assert m.field.resolution != res0  # upsampled
        assert not bool(m.field.occ.all())  # the occupancy mask pruned something
    # state_dict round trip into a fresh model (other grid resolution, all-True mask) is exact
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    m2 = RadianceModel(cfg, chair32.bbox, chair32.near, chair32.far, True)
    m2.load_state_dict(torch.load(buf))
    cam = views[3].camera
    a, b = m.render_image(cam), m2.render_image(cam)
    for k in ("rgb", "depth", "opacity", "beta2"):
        assert np.array_equal(a[k], b[k]), k
    assert a["rgb"].shape == (32, 32, 3) and a["beta2"].shape == (32, 32)


def test_grid_lookup_equals_grid_sample_in_value_and_gradient():
    """The channels-last gather is trilinear interpolation exactly as grid_sample computes it
    (align_corners=True, border padding): values, and gradients to the grid and to the points,
    inside the box, on its faces and outside it."""
    import torch.nn.functional as F

    torch.manual_seed(0)
    bbox = np.array([[-1.0, -0.5, -0.25], [1.0, 0.5, 0.75]])  # unequal sides: (Z, Y, X) = (9, 9, 17)
    f = GridConfig(grid_res=(17,), upsample_at=()).build(bbox, with_beta=False, beta_init=0.1, device="cpu")
    grid = torch.randn(*f.resolution, 5, requires_grad=True)  # (Z, Y, X, C)
    lo, hi = torch.tensor(bbox[0]).float(), torch.tensor(bbox[1]).float()
    x = lo + (hi - lo) * (torch.rand(400, 3) * 1.4 - 0.2)  # a fifth of the way outside on every side
    x = torch.cat([x, lo[None], hi[None], torch.stack([lo[0], hi[1], lo[2]])[None]]).requires_grad_(True)
    ours = f._lerp(grid, f.corners(x))  # (P, C)
    planes = grid.permute(3, 0, 1, 2)[:, None]  # (C, 1, Z, Y, X): one volume per channel
    g = ((x - lo) / (hi - lo) * 2 - 1).view(1, 1, 1, -1, 3).expand(5, 1, 1, -1, 3)
    ref = F.grid_sample(planes, g, mode="bilinear", padding_mode="border", align_corners=True).view(5, -1).t()
    torch.testing.assert_close(ours, ref, atol=1e-5, rtol=1e-5)
    w = torch.randn_like(ref)
    g_ours = torch.autograd.grad((ours * w).sum(), (grid, x))
    g_ref = torch.autograd.grad((ref * w).sum(), (grid, x))
    torch.testing.assert_close(g_ours[0], g_ref[0], atol=1e-5, rtol=1e-5)
    inside = ((x > lo) & (x < hi)).all(-1)  # on and outside the faces the clamp's gradient is a convention
    torch.testing.assert_close(g_ours[1][inside], g_ref[1][inside], atol=1e-3, rtol=1e-4)
    assert f._lerp(grid, f.corners(torch.zeros(0, 3))).shape == (0, 5)  # no sample (e.g. nothing occupied)


def test_query_colours_each_kept_sample_at_its_own_point_under_a_partial_mask():
    """The colour(w) that query returns looks up the corners of the samples it keeps, not of
    others: with half the grid pruned, its rgb equals color() at exactly those points."""
    m = make("grid")
    bump_density(m)
    f = m.field
    with torch.no_grad():
        f.feat_grid.normal_()
        f.occ[..., : f.occ.shape[2] // 2] = False  # prune the x < 0 half
    o, d = random_rays(64)
    x = o[:, None, :] + torch.linspace(1.0, 5.0, 32)[None, :, None] * d[:, None, :]  # (64, 32, 3)
    sigma, colour = f.query(x, d)
    assert 0 < int((sigma > 0).sum()) < sigma.numel()  # some samples pruned, some kept
    w = (sigma > 0).float() * 0.5  # any weight above the threshold on every occupied sample
    keep, rgb, raw = colour(w, None)
    assert keep.numel() > 0
    want, want_raw = f.color(x.reshape(-1, 3)[keep], d[keep // 32])
    torch.testing.assert_close(rgb, want)
    torch.testing.assert_close(raw, want_raw)


def test_colour_of_a_subset_of_rays_looks_up_those_rays_samples():
    """colour(w, rows) with w the weights of some rays only (the renderer composites the rays that have
    density): the same samples and colours as colour() over every ray, at those rays."""
    m = make("grid")
    bump_density(m)
    f = m.field
    with torch.no_grad():
        f.feat_grid.normal_()
        f.occ[..., : f.occ.shape[2] // 2] = False
    o, d = random_rays(64)
    x = o[:, None, :] + torch.linspace(1.0, 5.0, 32)[None, :, None] * d[:, None, :]
    sigma, colour = f.query(x, d)
    w = (sigma > 0).float() * 0.5
    rows = torch.nonzero(w.amax(-1) > 0).squeeze(-1)[::2]  # every other ray that has density
    keep_all, rgb_all, _ = colour(w, None)
    keep, rgb, _ = colour(w.index_select(0, rows), rows)
    as_all = rows[keep // 32] * 32 + keep % 32  # the subset's samples among all
    torch.testing.assert_close(rgb, rgb_all[torch.searchsorted(keep_all, as_all)])


def test_a_ray_without_density_is_background_and_the_others_render_as_if_all_were_composited():
    """The renderer composites only the rays with density somewhere; a ray with none renders its
    background exactly, and every other ray as it did when all rays were composited (here: a field whose
    empty space holds a density of 1e-30 instead of 0, so that every ray is composited)."""

    class Slab:  # density 3 in |z| < 0.3, `empty` elsewhere; colour 0.5 + 0.3 x, beta raw 0
        with_beta = True

        def __init__(self, empty: float):
            self.empty = empty

        def query(self, x, d):
            sigma = torch.where(x[..., 2].abs() < 0.3, 3.0, self.empty)
            flat = x.reshape(-1, 3)

            def colour(w, rows):
                at = (
                    torch.arange(flat.shape[0])
                    if rows is None
                    else (rows[:, None] * x.shape[1] + torch.arange(x.shape[1])).reshape(-1)
                )
                return torch.arange(w.numel()), (0.5 + 0.3 * flat[at, :1]).expand(-1, 3), torch.zeros(len(at))

            return sigma, colour

        def color(self, x, d):
            return (0.5 + 0.3 * x[:, :1]).expand(-1, 3), None

    o = torch.tensor([[0.0, 0.0, 3.0], [0.9, 0.0, 3.0], [0.5, 0.2, -3.0], [-3.0, 0.3, 0.6]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # the last: no slab
    kw = dict(bbox=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=6.0, n_samples=16, training=False, beta_min=0.1)
    for background in ("white", "last"):
        got = render_rays(Slab(0.0), o, d, background=background, **kw)
        want = render_rays(Slab(1e-30), o, d, background=background, **kw)
        for k in ("rgb", "depth", "opacity", "beta2"):
            torch.testing.assert_close(got[k], want[k], atol=1e-6, rtol=0)
        assert got["opacity"][3] == 0 and got["depth"][3] == 6.0 and got["beta2"][3] == pytest.approx(0.01)
        far_end = 0.5 + 0.3 * (-1.0 + 2.0 * 15.5 / 16)  # "last": the colour at the ray's far sample, x = 0.9375
        assert got["rgb"][3].tolist() == pytest.approx([1.0] * 3 if background == "white" else [far_end] * 3)


def test_the_grids_gradient_accumulates_in_place_as_autograds_would():
    """gather_rows: a grid parameter's lookups add their gradient into grid.grad in place, kept across steps
    and zeroed in place by zero_grad(set_to_none=False); the same gradient as autograd's own gather, and so
    the same Adam step."""
    from flipviz.model.optim import gather_rows

    torch.manual_seed(0)
    grid = torch.nn.Parameter(torch.randn(4, 5, 6, 3))
    ref = grid.detach().clone().requires_grad_(True)
    opt, opt_ref = (torch.optim.Adam([p], lr=0.1) for p in (grid, ref))
    buffers = set()
    for _ in range(3):
        idx = torch.randint(0, 120, (50,))  # with repeats, and a second lookup (as the TV regulariser's)
        idx2, w = torch.randint(0, 120, (20,)), torch.randn(50, 3)
        loss = (gather_rows(grid, idx) * w).sum() + gather_rows(grid, idx2).pow(2).sum()
        loss_ref = (ref.view(-1, 3)[idx] * w).sum() + ref.view(-1, 3)[idx2].pow(2).sum()
        opt.zero_grad(set_to_none=False)
        opt_ref.zero_grad()
        loss.backward()
        loss_ref.backward()
        buffers.add(grid.grad.data_ptr())
        torch.testing.assert_close(grid.grad, ref.grad)
        opt.step()
        opt_ref.step()
        torch.testing.assert_close(grid, ref)
    assert len(buffers) == 1  # one buffer for every step
    with torch.no_grad():
        assert gather_rows(grid, idx).grad_fn is None  # no graph outside autograd


def test_checkpoints_of_planar_grids_load_into_channels_last_grids():
    """A run saved with the grids as (C, 1, Z, Y, X) volumes loads to the same field."""
    m = make("grid")
    bump_density(m)
    with torch.no_grad():
        m.field.feat_grid.normal_()
    state = m.state_dict()
    old = {
        k: (v.permute(3, 0, 1, 2)[:, None].contiguous() if k.endswith(("density_grid", "feat_grid")) else v)
        for k, v in state.items()
    }
    m2 = make("grid")
    m2.load_state_dict(old)
    x = torch.rand(100, 3) * 2 - 1
    torch.testing.assert_close(m2.field.density(x), m.field.density(x))
    torch.testing.assert_close(
        m2.field.color(x, x / x.norm(dim=-1, keepdim=True))[0], m.field.color(x, x / x.norm(dim=-1, keepdim=True))[0]
    )


def test_pose_gradients_flow_through_grid(chair32):
    """Ray origins/directions from a c2w with requires_grad get gradients (what BA needs)."""
    views = ring(chair32)
    m = RadianceModel(
        ModelConfig(GridConfig(grid_res=(24,), upsample_at=()), n_samples=48), chair32.bbox, 2.0, 6.0, False
    )
    fit(m, views, steps=10, batch_rays=1024)
    bank = RayBank.from_images([views[0].camera], [views[0].rgb])
    c2w = torch.as_tensor(views[0].camera.c2w, dtype=torch.float32).expand(len(bank), 4, 4).clone().requires_grad_(True)
    o, d = rays_from_c2w(c2w, bank.dirs_cam)
    loss = (m.render_rays(o, d, training=False)["rgb"] - bank.rgb).pow(2).mean()
    loss.backward()
    assert c2w.grad is not None and c2w.grad.abs().sum() > 0


def test_inference_renders_the_whole_box_from_any_distance():
    """A novel camera far outside [near, far] sees the object: only the box bounds sampling."""
    model = RadianceModel(small_config("grid", n_samples=64), BBOX, near=2.0, far=4.0, with_beta=True, device="cpu")
    o, d = random_rays(256)
    with torch.no_grad():
        here = model.render_rays(o, d, training=False)
        far_away = model.render_rays(o - 20.0 * d, d, training=False)
    assert float(here["opacity"].max()) > 0.05  # the untrained grid has some density
    for k in ("rgb", "opacity", "beta2"):
        assert torch.allclose(here[k], far_away[k], atol=1e-5), k


def test_barf_coarse_to_fine_opens_the_positional_encoding_bands_with_training():
    """BARF's window (0.1, 0.5): no band of x before 10% of training, each band k opening in turn,
    all of them from 50% on. The model's per-step schedule drives it (a window pinned open is BARF off)."""
    torch.manual_seed(0)
    bbox = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    model = RadianceModel(
        ModelConfig(field=NerfConfig(barf_c2f=(0.1, 0.5)), n_samples=8), bbox, 0.5, 4.0, with_beta=False
    )
    weights = []
    for step in (0, 10, 30, 50, 100):
        model.update_schedule(step, 100)
        weights.append(model.field.barf_weights())
    n = model.field.cfg.pe
    assert float(weights[0].max()) == 0.0 and float(weights[1].max()) == 0.0  # before and at the window's start
    opening = weights[2]  # half-way through the window: the first n/2 bands open, the last ones shut
    assert float(opening[0]) == 1.0 and float(opening[-1]) == 0.0 and 0 < int((opening == 1.0).sum()) < n
    assert torch.all(weights[3] == 1.0) and torch.all(weights[4] == 1.0)
    # the encoding of x follows: at step 0 two points that differ only in high frequencies encode alike
    model.update_schedule(0, 100)
    x = torch.tensor([[0.1, 0.2, 0.3]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    wiggle = x + torch.tensor([[2.0 / 2 ** (n - 1), 0.0, 0.0]])  # a whole period of the top band (x in [-1, 1] -> pi x)
    near = model.field(x, d)[0], model.field(wiggle, d)[0]
    model.update_schedule(100, 100)
    far = model.field(x, d)[0], model.field(wiggle, d)[0]
    assert abs(float(near[0] - near[1])) < abs(float(far[0] - far[1]))
