"""The live 3D preview: the field baked into Gaussian splats that the browser draws at full frame rate.

Every `period_s` while training (and at each new run) the render worker asks the trainer for the
field's opaque cells (`Trainer.point_cloud`, a few hundred ms), one bake for all browsers, and
sends each browser its own splats (splats.py: one Gaussian per cell), coloured by RGB, by opacity,
or by beta^2 (where the variance head learned that the mirrored images disagree with the model);
*Preview drawn as* points shows the cells as squares instead. A browser shows the preview while
its camera moves, or always when it renders no view of its own; the exact server render replaces
it once the camera is still.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from flipviz.viz import palette
from flipviz.viz.app.guard import guard_choice
from flipviz.viz.app.render import BACKGROUND, RenderWorker
from flipviz.viz.run_view import RunView
from flipviz.viz.splats import Splats, cells_to_splats, solid_splats

COLOURS = ("RGB", "opacity", "beta^2")
STYLES = ("splats", "points")
POINT_BYTES = 9  # float16 xyz + uint8 rgb per point
MAPPED_FLOOR = 0.6  # the least opacity of a splat coloured by opacity: its colour must read
BETA2_SHOWN_PERCENT = 25  # beta^2 in 3D: the cells the model is least sure of, coloured (beta2_splats)
SHAPE_OPACITY = 0.12  # ... over the object's other solid cells in faint grey
BETA2_LEAST_SPAN = 0.5  # log10: the scale spans at least a factor of 3 in beta^2


def beta2_splats(baked: dict) -> tuple[Splats, tuple[float, float, str]]:
    """beta^2 in 3D, readable: the quarter of the baked cells the model is least sure of, coloured on this
    bake's own log scale (its 75th percentile up to its maximum) and more opaque the higher they are, over
    the object's solid cells in faint grey for its shape. Every cell at one opacity was a blob: on a
    symmetric object (the chair) nearly all beta^2 sit near the floor beta_min^2, and the faint cells fill
    the object's box."""
    log_b2, cell = np.log10(np.asarray(baked["beta2"], np.float64)), float(baked["cell"])
    lo = float(np.percentile(log_b2, 100 - BETA2_SHOWN_PERCENT))
    hi = max(float(log_b2.max()), lo + BETA2_LEAST_SPAN)  # a nearly even field stays dark and faint
    t = np.clip((log_b2 - lo) / (hi - lo), 0.0, 1.0)
    doubted, shape = t > 0, baked["solid"] & (t <= 0)
    grey = np.full((int(shape.sum()), 3), 190, np.uint8)
    splats = cells_to_splats(
        np.concatenate([baked["points"][shape], baked["points"][doubted]]),
        np.concatenate([grey, palette.colormap(log_b2[doubted], lo, hi)]),
        np.concatenate([np.full(len(grey), SHAPE_OPACITY, np.float32), 0.25 + 0.75 * t[doubted]]),
        cell,
    )
    return splats, (
        round(lo, 2),
        round(hi, 2),
        f"log10 beta^2 per cell: its top {BETA2_SHOWN_PERCENT}% (grey: the object)",
    )


class LivePreview:
    def __init__(
        self,
        server: viser.ViserServer,
        worker: RenderWorker,
        run: RunView,
        period_s: float = 5.0,
    ) -> None:
        self.server, self.worker, self.run = server, worker, run
        self.period_s = period_s
        self.baked: dict | None = None
        self.visible: dict[int, bool] = {}  # client id -> cloud shown
        self.handles: dict[int, viser.SceneNodeHandle] = {}
        self.last_bake_s = 0.0
        self._drawn: Splats | None = None  # the last bake as shown
        self._lock = threading.Lock()
        gui = server.gui
        self.enabled = gui.add_checkbox(
            "Live 3D preview", True, hint="The field as Gaussian splats, drawn by your browser"
        )
        self.colour = guard_choice(gui.add_dropdown("Preview colour", COLOURS, initial_value="RGB"), COLOURS)
        self.style = guard_choice(
            gui.add_dropdown(
                "Preview drawn as",
                STYLES,
                initial_value="splats",
                hint="splats: one Gaussian per cell; points: the cells as squares",
            ),
            STYLES,
        )
        self.colorbar = gui.add_image(np.full((46, 320, 3), 255, np.uint8), label="Preview scale", format="png")
        self.colorbar.visible = False
        self.status = gui.add_markdown("_The first bake comes with the first steps._")
        self.enabled.on_update(lambda _: self._apply_all())
        self.colour.on_update(lambda _: self._apply_all())
        self.style.on_update(lambda _: self._apply_all())

    @property
    def on(self) -> bool:
        return bool(self.enabled.value)

    # ---- baking -----------------------------------------------------------------------------
    def request(self, delay: float = 0.0) -> None:
        self.worker.submit("preview-bake", self._bake, priority=BACKGROUND, delay=delay)

    def _bake(self) -> None:
        step = self.run.step
        if self.on and (self.baked is None or self.baked.get("step") != step):  # the model changed since
            t = time.perf_counter()
            baked = self.run.point_cloud()
            if baked is not None:
                self.last_bake_s = time.perf_counter() - t
                with self._lock:
                    self.baked = dict(baked, step=step)
                self._apply_all()
        if self.run.training:
            self.request(delay=self.period_s)

    def clear(self) -> None:
        """A new run: the last run's splats, and their count, go until its first bake."""
        with self._lock:
            self.baked = None
        self._drawn = None
        self.status.content = "_Waiting for the new run's first bake..._"
        for cid in list(self.visible):
            self._client_scene(cid, lambda s: s.remove_by_name("/preview3d"))
        self.handles.clear()

    # ---- drawing ----------------------------------------------------------------------------
    def shown(self, baked: dict) -> tuple[Splats, tuple[float, float, str] | None]:
        """The cells to draw for the chosen colouring, as splats, and the colour scale.

        RGB and opacity show the solid cells; beta^2 adds the faint cells the model is most unsure
        of, on a log scale (per-cell variances span decades). RGB splats have
        the cells' own opacity; opacity-coloured ones at least MAPPED_FLOOR, so that their colour reads; beta^2 ones
        as beta2_splats draws them."""
        which, solid, cell = self.colour.value, baked["solid"], float(baked["cell"])
        if which == "beta^2" and "beta2" in baked:
            return beta2_splats(baked)
        alpha = baked["alpha"][solid]
        if which == "opacity":
            c = palette.colormap(alpha, 0.0, 1.0)
            return cells_to_splats(baked["points"][solid], c, alpha, cell, MAPPED_FLOOR), (
                0.0,
                1.0,
                "opacity of one cell",
            )
        return solid_splats(baked), None

    def set_visible(self, client_id: int, visible: bool) -> None:
        """Show or hide this client's cloud (the viewport renderer hides it under a still render)."""
        if self.visible.get(client_id) == visible:
            return
        self.visible[client_id] = visible
        handle = self.handles.get(client_id)
        if handle is not None:
            handle.visible = visible
        else:
            self._client_scene(client_id, lambda s: self._draw(s, client_id))

    def remove_client(self, client_id: int) -> None:
        self.visible.pop(client_id, None)
        self.handles.pop(client_id, None)

    def _apply_all(self) -> None:
        """Colour the last bake once for the chosen colouring, then send it to every client."""
        with self._lock:
            baked = self.baked
        splats, bar = self.shown(baked) if baked is not None else (None, None)
        self._drawn = splats
        self.colorbar.visible = bar is not None and self.on
        if bar is not None:
            self.colorbar.image = palette.colorbar(*bar)
        if splats is not None:
            kind, size = (
                ("splats", splats.nbytes) if self.style.value == "splats" else ("points", len(splats) * POINT_BYTES)
            )
            self.status.content = (
                f"{len(splats)} {kind} at step {baked['step']}, baked in {1000 * self.last_bake_s:.0f} ms, "
                f"{size / 2**20:.1f} MB per browser"
                if self.on
                else "_Preview off._"
            )
        for cid in list(self.visible):
            self._client_scene(cid, lambda s, cid=cid: self._draw(s, cid))

    def _draw(self, scene: viser.SceneApi, client_id: int) -> None:
        drawn = self._drawn
        if drawn is None or not self.on:
            scene.remove_by_name("/preview3d")
            self.handles.pop(client_id, None)
            return
        visible = self.visible.get(client_id, True)
        if self.style.value == "points":
            self.handles[client_id] = scene.add_point_cloud(
                "/preview3d",
                drawn.centers,
                drawn.rgbs,
                point_size=2.0 * drawn.sigma,
                point_shape="square",
                precision="float16",
                visible=visible,
            )
            return
        self.handles[client_id] = scene.add_gaussian_splats(
            "/preview3d",
            drawn.centers,
            drawn.covariances,
            drawn.rgbs.astype(np.float32) / 255.0,
            drawn.opacities[:, None],
            visible=visible,
        )

    def _client_scene(self, client_id: int, fn: Callable[[viser.SceneApi], None]) -> None:
        client = self.server.get_clients().get(client_id)
        if client is not None:
            fn(client.scene)
