"""The pixel probe: snapped to a view, click a pixel of it for its ground truth, render, |error|,
beta^2, depth and opacity, and a marker where the ray meets the surface.

The browser sends the click as a world ray from its camera; snapped, that camera is the view's, so
the ray's direction projects to the view's pixel (`pixel_of_ray`). The view is rendered at its own
resolution (through the RenderWorker, as a user request) and the pixel read from it (`read_pixel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser

from flipviz.data.cameras import Camera
from flipviz.viz import palette
from flipviz.viz.app.render import RenderWorker, Snapped
from flipviz.viz.run_view import RunView

HELP = "_Pixel probe: snap to a view, then click a pixel of it in the 3D view._"


def pixel_of_ray(cam: Camera, direction: np.ndarray) -> tuple[int, int] | None:
    """The (row, column) of `cam` whose ray leaves its centre along `direction` (None: outside the image)."""
    rows, cols, inside = cam.project(cam.center[None] + np.asarray(direction, np.float64)[None])
    return (int(rows[0]), int(cols[0])) if inside[0] else None


@dataclass
class PixelReading:
    """What one pixel of a view holds, rendered at `step`."""

    view: str
    row: int
    col: int
    step: int
    rgb: np.ndarray  # (3,) the render
    gt: np.ndarray | None  # (3,) the ground truth (flipped for a mirror), where known
    depth: float  # expected ray depth (scene units along the ray)
    opacity: float
    beta2: float | None  # rendered variance beta_hat^2, where the model has it
    point: np.ndarray  # (3,) the world point at the rendered depth

    @property
    def error(self) -> float | None:
        """|render - ground truth|, mean over RGB (the |error| maps' quantity)."""
        return float(np.abs(self.rgb - self.gt).mean()) if self.gt is not None else None

    def table(self) -> str:
        def rgb(c: np.ndarray) -> str:
            return "(" + ", ".join(f"{v:.3f}" for v in c) + ")"

        rows = [
            ("render RGB", rgb(self.rgb)),
            ("ground truth RGB", rgb(self.gt) if self.gt is not None else "unknown"),
            ("abs error (mean RGB)", f"{self.error:.3f}" if self.error is not None else "-"),
            ("beta^2", f"{self.beta2:.4f}" if self.beta2 is not None else "- (no beta^2 in this method)"),
            ("depth", f"{self.depth:.3f}"),
            ("opacity", f"{self.opacity:.3f}"),
        ]
        head = f"**Pixel ({self.row}, {self.col})** of **{self.view}** (row, column), step {self.step}\n\n"
        head += "| | |\n|---|---|\n"
        return head + "\n".join(f"| {k} | {v} |" for k, v in rows)


def read_pixel(
    out: dict[str, np.ndarray], cam: Camera, reference: np.ndarray | None, row: int, col: int, view: str, step: int
) -> PixelReading:
    """One pixel of a render of `cam` (`out`: rgb, depth, opacity and maybe beta2, at cam's resolution)."""
    _, dirs = cam.rays()
    d = dirs[row * cam.width + col].astype(np.float64)
    depth = float(out["depth"][row, col])
    gt = (
        np.asarray(reference[row, col], np.float64)
        if reference is not None and reference.shape[:2] == (cam.height, cam.width)
        else None
    )
    b2 = out.get("beta2")
    return PixelReading(
        view,
        row,
        col,
        step,
        np.asarray(out["rgb"][row, col], np.float64),
        gt,
        depth,
        float(out["opacity"][row, col]),
        float(b2[row, col]) if b2 is not None else None,
        cam.center + depth * d,
    )


class PixelProbe:
    """The probe's panel (in the Views tab) and its marker in the 3D view; shared by all clients."""

    def __init__(
        self, server: viser.ViserServer, worker: RenderWorker, run: RunView, after: viser.GuiMarkdownHandle
    ) -> None:
        self.server, self.worker, self.run = server, worker, run
        self.text = server.gui.add_markdown(HELP, order=after.order + 0.5)  # right under `after`, above the images
        self.reading: PixelReading | None = None

    def click(self, snapped: Snapped | None, direction: np.ndarray) -> None:
        """A click in the 3D view along `direction` (world); `snapped`: the view the clicking browser is at."""
        if snapped is None:
            self.text.content = "_Pixel probe: your camera is not at a view. Snap to one first, then click a pixel._"
            return
        px = pixel_of_ray(snapped.camera, direction)
        if px is None:
            self.text.content = f"_Pixel probe: that click is outside **{snapped.name}**'s image._"
            return
        self.worker.submit("probe", lambda: self._read(snapped, *px), priority=0)

    def _read(self, snapped: Snapped, row: int, col: int) -> None:
        cam = snapped.camera
        out = self.run.render(cam)
        if out is None:
            return
        reading = read_pixel(out, cam, snapped.reference, row, col, snapped.name, self.run.step)
        self.reading = reading
        setup = self.run.setup
        r = 0.01 * float(setup.sphere_radius) if setup is not None else 0.04
        toward_camera = cam.center - reading.point
        toward_camera /= max(float(np.linalg.norm(toward_camera)), 1e-9)
        self.server.scene.add_icosphere(  # on the ray, just in front of the surface (not hidden in it)
            "/probe",
            radius=r,
            color=palette.PROBE,
            position=reading.point + r * toward_camera,
            cast_shadow=False,
            receive_shadow=False,
        )
        self.text.content = reading.table()

    def clear(self) -> None:
        """A new run, or the browser left the view: the reading and its marker go."""
        if self.reading is not None:
            self.server.scene.remove_by_name("/probe")
        self.reading = None
        self.text.content = HELP
