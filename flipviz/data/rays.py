"""All pixels of a set of posed views as one flat bank of rays, on the training device."""

from __future__ import annotations

from dataclasses import dataclass

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
