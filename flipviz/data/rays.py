"""All pixels of a set of posed views as one flat bank of rays, on the training device."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from flipviz.data.cameras import Camera, pixel_directions


@dataclass
class RayBank:
    """Per pixel: its view's index, its camera-frame direction and its colour.

    World rays are made each step from the views' current poses (`rays_from_c2w`), so that
    refined poses receive gradients.
    """

    view: torch.Tensor  # (N,) long: index of the pixel's view
    dirs_cam: torch.Tensor  # (N, 3) float32 camera-frame directions (z = -1)
    rgb: torch.Tensor  # (N, 3) float32 target colours

    @classmethod
    def from_images(
        cls,
        cameras: list[Camera],
        images: list[np.ndarray],
        device: str | torch.device = "cpu",
        keep: list[np.ndarray | None] | None = None,
    ) -> RayBank:
        """Every pixel of every view; `keep[i]` (H, W) bool, when given, keeps only those of view i."""
        views, dirs, rgbs = [], [], []
        for i, (cam, img) in enumerate(zip(cameras, images, strict=True)):
            if img.shape[:2] != (cam.height, cam.width):
                raise ValueError(
                    f"view {cam.name!r}: image {img.shape[:2]} does not match camera {cam.height}x{cam.width}"
                )
            k = keep[i].reshape(-1) if keep is not None and keep[i] is not None else slice(None)
            views.append(np.full(cam.width * cam.height, i, np.int64)[k])
            dirs.append(pixel_directions(cam.width, cam.height, cam.focal)[k])
            rgbs.append(img.reshape(-1, 3)[k])
        t = lambda a, dt: torch.from_numpy(np.concatenate(a)).to(device=device, dtype=dt)  # noqa: E731
        return cls(t(views, torch.long), t(dirs, torch.float32), t(rgbs, torch.float32))

    def __len__(self) -> int:
        return int(self.view.shape[0])

    def sample(self, n: int, generator: torch.Generator, first: int | None = None) -> torch.Tensor:
        """n random ray indices (with replacement) among the `first` rays (None: all), drawn on the CPU
        for reproducibility."""
        return torch.randint(0, len(self) if first is None else first, (n,), generator=generator).to(self.view.device)

    @cached_property
    def counts(self) -> torch.Tensor:
        """(V,) the rays of each view, on the CPU."""
        return torch.bincount(self.view.cpu())

    def sample_views(self, n: int, generator: torch.Generator, views: torch.Tensor) -> torch.Tensor:
        """n random ray indices (with replacement) among the rays of `views` (increasing view indices),
        uniform over those rays. Each view's rays are contiguous in the bank (`from_images`): a draw u among
        the kept rays is the u-th ray of their concatenation. The views 0..k-1 draw as `sample(first=...)`."""
        counts = self.counts
        lengths = counts[views.cpu()]  # (K,)
        ends = lengths.cumsum(0)  # (K,) where each kept view's rays end among the kept ones
        u = torch.randint(0, int(ends[-1]), (n,), generator=generator)  # (n,)
        k = torch.searchsorted(ends, u, right=True)  # (n,) which kept view each draw falls in
        starts = counts.cumsum(0) - counts  # (V,) where each view's rays start in the bank
        return (starts[views.cpu()][k] + u - (ends - lengths)[k]).to(self.view.device)
