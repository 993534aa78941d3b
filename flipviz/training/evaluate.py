"""Scores of renders against ground truth: PSNR, SSIM and LPIPS (AlexNet, when its weights exist),
and three that see the object's structure rather than the white background around it:

    iou          silhouette IoU: rendered opacity > 0.5 against ground-truth alpha > 0.5
    psnr_object  PSNR inside the object: over the union of the true and the rendered silhouettes
                 (a render that keeps unobserved space white scores nothing there for it)
    depth_abs    mean |rendered depth - true depth| over the true silhouette, in world units, where
                 the ground truth has depth (built-in scenes: the ray caster's first hit)

LPIPS (Zhang et al. 2018, v0.1, AlexNet) is implemented here because torchvision is not a
dependency: AlexNet's `features` exactly as torchvision builds them, loaded from torchvision's
checkpoint in the torch hub cache, plus the LPIPS linear heads (`alex.pth`). When either file is
missing the metric is the string "unavailable" with a one-line reason: never a made-up number.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from flipviz.data.cameras import Camera, View
from flipviz.model.objective import psnr as psnr_from_mse
from flipviz.training.events import ImagesEvent, RenderedView
from flipviz.training.methods import TrainView

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"  # torchvision's AlexNet ImageNet weights
LPIPS_FILE = "alex.pth"  # LPIPS v0.1 linear layers for AlexNet
UNAVAILABLE = "unavailable"
SLOW_EVALUATION_S = 2.0  # an evaluation running longer says which view it is at (announced)


def image_psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR (dB) of an image against its ground truth, both in [0, 1] (the prediction is clipped)."""
    return psnr_from_mse(np.mean((np.clip(pred, 0, 1).astype(np.float64) - gt.astype(np.float64)) ** 2))


def silhouette(alpha: np.ndarray) -> np.ndarray:
    """The object's pixels: alpha (or rendered opacity) > 0.5."""
    return np.asarray(alpha) > 0.5


def silhouette_iou(opacity: np.ndarray, alpha: np.ndarray) -> float:
    """|pred & true| / |pred | true| of the two silhouettes; 1.0 when both are empty."""
    p, t = silhouette(opacity), silhouette(alpha)
    union = np.logical_or(p, t).sum()
    return float(np.logical_and(p, t).sum() / union) if union else 1.0


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) over the pixels of `mask` only (nan when it is empty)."""
    if not mask.any():
        return float("nan")
    d = np.clip(pred, 0, 1).astype(np.float64)[mask] - gt.astype(np.float64)[mask]
    return psnr_from_mse(float(np.mean(d**2)))


def depth_abs_error(depth: np.ndarray, true_depth: np.ndarray, alpha: np.ndarray) -> float:
    """Mean |depth - true depth| over the true silhouette where the true depth is finite (nan: none)."""
    m = silhouette(alpha) & np.isfinite(true_depth)
    return float(np.mean(np.abs(depth[m] - true_depth[m]))) if m.any() else float("nan")


def structure_scores(
    pred: np.ndarray,
    gt: np.ndarray,
    opacity: np.ndarray,
    alpha: np.ndarray | None,
    depth: np.ndarray | None = None,
    true_depth: np.ndarray | None = None,
) -> dict:
    """iou, psnr_object (and depth_abs where the true depth is known) of one view; {} without alpha."""
    if alpha is None:
        return {}
    out = {
        "iou": silhouette_iou(opacity, alpha),
        "psnr_object": masked_psnr(pred, gt, silhouette(opacity) | silhouette(alpha)),
    }
    if depth is not None and true_depth is not None:
        out["depth_abs"] = depth_abs_error(depth, true_depth, alpha)
    return out


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(np.clip(pred, 0, 1), gt, channel_axis=-1, data_range=1.0))


# ---------------------------------------------------------------------------------------- LPIPS


def _lpips_weight_paths() -> tuple[Path | None, Path | None, str]:
    """Locate (alexnet, lpips-linear) weight files; the reason string says what is missing."""
    ckpt = Path(torch.hub.get_dir()) / "checkpoints"
    alex = ckpt / ALEXNET_FILE
    lin_candidates = [ckpt / LPIPS_FILE]
    try:  # the `lpips` package ships the linear weights, if it happens to be installed
        import lpips

        lin_candidates.append(Path(lpips.__file__).parent / "weights" / "v0.1" / LPIPS_FILE)
    except Exception:
        pass
    lin = next((p for p in lin_candidates if p.is_file()), None)
    missing = []
    if not alex.is_file():
        missing.append(str(alex))
    if lin is None:
        missing.append(" or ".join(str(p) for p in lin_candidates))
    reason = "" if not missing else "LPIPS weights not found: " + "; ".join(missing)
    return (alex if alex.is_file() else None), lin, reason


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 with AlexNet: sum over conv1..conv5 of spatially averaged w_l . (f0 - f1)^2."""

    CHANNELS = (64, 192, 384, 256, 256)

    def __init__(self) -> None:
        super().__init__()
        # torchvision.models.alexnet().features, index for index (so its state_dict loads as is)
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2),
            nn.ReLU(inplace=False),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2),
            nn.ReLU(inplace=False),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1),
            nn.ReLU(inplace=False),
            nn.Conv2d(384, 256, 3, padding=1),
            nn.ReLU(inplace=False),
            nn.Conv2d(256, 256, 3, padding=1),
            nn.ReLU(inplace=False),
            nn.MaxPool2d(3, 2),
        )
        self.slices = ((0, 2), (2, 5), (5, 8), (8, 10), (10, 12))  # outputs relu1..relu5
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in self.CHANNELS)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    def load(self, alex_path: Path, lin_path: Path) -> LPIPSAlex:
        sd = torch.load(alex_path, map_location="cpu", weights_only=True)
        self.features.load_state_dict({k[len("features.") :]: v for k, v in sd.items() if k.startswith("features.")})
        lin = torch.load(lin_path, map_location="cpu", weights_only=True)
        for i, conv in enumerate(self.lins):  # LPIPS keys: lin{i}.model.1.weight (after a Dropout)
            conv.weight.data.copy_(lin[f"lin{i}.model.1.weight"])
        return self.eval()

    def _feats(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        out = []
        for a, b in self.slices:
            for layer in self.features[a:b]:
                x = layer(x)
            out.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))  # unit-normalise channels
        return out

    @torch.no_grad()
    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> torch.Tensor:
        """img0, img1: (B, 3, H, W) in [-1, 1] -> (B,) distances."""
        f0, f1 = self._feats(img0), self._feats(img1)
        return sum(lin((a - b) ** 2).mean(dim=(1, 2, 3)) for lin, a, b in zip(self.lins, f0, f1))


_LPIPS_CACHE: dict[tuple[str, str], LPIPSAlex] = {}


def load_lpips() -> tuple[LPIPSAlex | None, str]:
    """(network, "") when the weights are present locally, else (None, one-line reason)."""
    alex, lin, reason = _lpips_weight_paths()
    if alex is None or lin is None:
        return None, reason
    key = (str(alex), str(lin))
    if key not in _LPIPS_CACHE:
        try:
            _LPIPS_CACHE[key] = LPIPSAlex().load(alex, lin)
        except Exception as e:  # a corrupt or foreign file: say so, don't guess
            return None, f"LPIPS weights could not be loaded: {type(e).__name__}: {e}".splitlines()[0]
    return _LPIPS_CACHE[key], ""


def lpips_distance(net: LPIPSAlex, pred: np.ndarray, gt: np.ndarray) -> float:
    to_t = lambda im: torch.from_numpy(np.clip(im, 0, 1).astype(np.float32)).permute(2, 0, 1)[None] * 2 - 1  # noqa: E731
    return float(net(to_t(pred), to_t(gt))[0])


# ------------------------------------------------------------------------------------ scoring


STRUCTURE = ("iou", "psnr_object", "depth_abs")


def blank_scores(gts: list[np.ndarray]) -> dict[str, float]:
    """PSNR and SSIM of an all-white image against each view, averaged: the score of a render that shows
    nothing at all. A table's scores mean something only well above it (lego: about 10 dB)."""
    white = [np.ones_like(g) for g in gts]
    return {
        "blank_psnr": float(np.mean([image_psnr(w, g) for w, g in zip(white, gts)])),
        "blank_ssim": float(np.mean([ssim(w, g) for w, g in zip(white, gts)])),
    }


def score_renders(scene, views: list, renders: list[dict[str, np.ndarray]]) -> dict:
    """`score_views` of renders of `views` (their rgb, opacity, depth) against the views' ground truth, with
    the structure scores (the scene's true depth where known) and a white image's scores beside."""
    from flipviz.data.builtin import true_depth

    structure = [
        structure_scores(o["rgb"], v.rgb, o["opacity"], v.alpha, o["depth"], true_depth(scene, v.camera))
        for o, v in zip(renders, views)
    ]
    gts = [v.rgb for v in views]
    return score_views([o["rgb"] for o in renders], gts, [v.name for v in views], structure) | blank_scores(gts)


def score_views(
    preds: list[np.ndarray], gts: list[np.ndarray], names: list[str], structure: list[dict] | None = None
) -> dict:
    """Mean and per-view PSNR / SSIM / LPIPS, and the structure scores given per view (`structure_scores`).
    LPIPS is "unavailable" (+ lpips_reason) without weights."""
    net, reason = load_lpips()
    per_view = []
    for i, (name, p, g) in enumerate(zip(names, preds, gts)):
        row = {"name": name, "psnr": image_psnr(p, g), "ssim": ssim(p, g)}
        row["lpips"] = lpips_distance(net, p, g) if net is not None else UNAVAILABLE
        row.update(structure[i] if structure else {})
        per_view.append(row)
    out = {
        "psnr": float(np.mean([r["psnr"] for r in per_view])) if per_view else float("nan"),
        "ssim": float(np.mean([r["ssim"] for r in per_view])) if per_view else float("nan"),
        "lpips": float(np.mean([r["lpips"] for r in per_view])) if net is not None and per_view else UNAVAILABLE,
        "per_view": per_view,
    }
    for key in STRUCTURE:  # over the views that have it (nan-free)
        vals = [r[key] for r in per_view if key in r and np.isfinite(r[key])]
        if vals:
            out[key] = float(np.mean(vals))
    if net is None:
        out["lpips_reason"] = reason
    return out


def announced(
    render: Callable[[Camera], dict[str, np.ndarray]], say: Callable[[str], None], what: str, n: int
) -> Callable[[Camera], dict[str, np.ndarray]]:
    """`render` for an evaluation of `n` views that, once it has taken longer than SLOW_EVALUATION_S, says
    which view it is at (the paper's NeRF on a CPU: minutes a view)."""
    t0, done = time.monotonic(), [0]

    def announced_render(camera: Camera) -> dict[str, np.ndarray]:
        done[0] += 1
        if time.monotonic() - t0 > SLOW_EVALUATION_S:
            say(f"{what}: view {done[0]} of {n} ({time.monotonic() - t0:.0f} s so far)")
        return render(camera)

    return announced_render


def images_event(
    step: int,
    render: Callable[[Camera], dict[str, np.ndarray]],
    tests: list[View],
    mirrors: list[tuple[TrainView, Camera]],
    test_renders: list[dict[str, np.ndarray]] | None = None,
) -> ImagesEvent:
    """The unobserved test views (`test_renders` where already made) and the mirrored views (each with its
    current camera), rendered by `render`, with their ground truth and the test views' mean PSNR."""

    def rendered(kind, cam: Camera, gt: np.ndarray, r: dict[str, np.ndarray] | None = None) -> RenderedView:
        r = render(cam) if r is None else r
        return RenderedView(cam.name, kind, cam, r["rgb"], r["depth"], r["opacity"], r.get("beta2"), gt)

    rs = test_renders or [None] * len(tests)
    shown = [rendered("test", v.camera, v.rgb, r) for v, r in zip(tests, rs)]
    flipped = [rendered("mirror", c, v.image) for v, c in mirrors]
    scalars = {"test_psnr": float(np.mean([image_psnr(t.rgb, t.gt) for t in shown]))} if shown else {}
    return ImagesEvent(step, shown, flipped, scalars)
