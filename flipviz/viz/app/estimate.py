"""The Mirror tab's estimated plane: found from the run's inputs on demand, shown with its
confidence and its score against the normal's azimuth, and handed to the plane editor by one button.

The estimate (training/plane_estimate.py) is a short B/L fit of the inputs, then the reflection
that maps what they saw onto itself. A run that estimated its plane at setup shows that one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from flipviz.data.cameras import WORLD_UP, azimuth_deg
from flipviz.data.dataset import Plane
from flipviz.geometry.symmetry import CONFIDENT, PlaneEstimate, plane_error
from flipviz.viz import palette
from flipviz.viz.run_view import RunView

HELP = (
    "_No estimate yet. **Estimate plane** finds the mirror plane from the input views alone (a short B/L fit, "
    "then the reflection that maps what the inputs saw onto itself), with a confidence._"
)


def score_chart(est: PlaneEstimate, up: np.ndarray, size: tuple[int, int] = (400, 240)) -> np.ndarray:
    """uint8 RGB chart: the best score of the vertical planes against their normal's azimuth, the
    estimate's azimuth marked (matplotlib, drawn off-screen). Azimuth is circular with period 180 (a
    normal and its negative are one plane), so the axis runs 90 degrees either side of the estimate:
    a peak at 0 / 180 is drawn whole, in the middle, not split across the two edges."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    az = azimuth_deg(est.plane.normal, up) % 180.0
    x = az + (np.asarray(est.azimuth_deg) - az + 90.0) % 180.0 - 90.0  # each azimuth within 90 deg of the estimate
    order = np.argsort(x)
    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    ax = fig.add_subplot()
    ax.plot(x[order], np.asarray(est.azimuth_score)[order], color=palette.hex_color(palette.MIRROR_PLANE), lw=1.8)
    ax.axvline(az, color="0.3", ls="--", lw=1)
    ax.set(xlabel="normal azimuth about up (deg, mod 180)", ylabel="score", xlim=(az - 90.0, az + 90.0))
    ax.set_title(f"estimate at {az:.1f} deg, confidence {est.confidence:.2f}", fontsize=9)
    ax.tick_params(labelsize=8)
    fig.tight_layout(pad=0.4)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


class PlaneEstimatePanel:
    """The "Estimated plane" folder: Estimate plane, the estimate in words and as a chart, Use it."""

    def __init__(
        self,
        server: viser.ViserServer,
        run: RunView,
        training_plane: Callable[[], Plane | None],
        on_use: Callable[[Plane], None],
    ) -> None:
        self.server, self.run, self.training_plane = server, run, training_plane
        gui = server.gui
        with gui.add_folder("Estimated plane") as self.folder:
            self.text = gui.add_markdown(HELP)
            self.against = gui.add_markdown("")  # the estimate against the plane training uses now
            self.button = gui.add_button(
                "Estimate plane",
                icon=viser.Icon.SEARCH,
                hint="A short B/L fit of the inputs, then the reflection that maps it onto itself",
            )
            self.use_button = gui.add_button("Use estimated plane", icon=viser.Icon.CHECK, disabled=True)
        self.chart: viser.GuiImageHandle | None = None
        self.estimate: PlaneEstimate | None = None
        self._busy = threading.Lock()  # one estimate at a time
        self.button.on_click(lambda _: self.start())
        self.use_button.on_click(lambda _: self.estimate is not None and on_use(self.estimate.plane))

    def compare_with_training(self, refined_at: int | None = None) -> None:
        """The estimate against the plane training uses now, shown above it in the tab (refined by training
        at step `refined_at`, or where training started it: before, the line kept the starting plane)."""
        est, plane = self.estimate, self.training_plane()
        if est is None or plane is None:
            self.against.content = ""
            return
        deg, off = plane_error(est.plane, plane)
        which = "where training started it" if refined_at is None else f"as training refined it at step {refined_at}"
        self.against.content = f"Against the plane training uses now ({which}): {deg:.2f} deg, offset {off:.4f}."

    def start(self) -> None:
        """Estimate in a thread, a clock ticking in the text meanwhile; the run's own estimate at once."""
        setup = self.run.setup
        if setup is not None and setup.plane_estimate is not None and self.estimate is setup.plane_estimate:
            self.show(self.estimate)  # the same inputs give the same plane: say so, at once
            self.text.content = (
                "_Already estimated when this run started (the same inputs give the same plane):_ " + self.text.content
            )
            return
        if not self._busy.acquire(blocking=False):
            return
        self.button.disabled = True
        done = threading.Event()

        def tick() -> None:  # the time so far, every second: training shares the CPU, so it may take minutes
            t0 = time.monotonic()
            while not done.is_set():
                self.text.content = (
                    f"_Estimating: a short B/L fit of the inputs, then the plane search... "
                    f"{time.monotonic() - t0:.0f} s (10-20 s on an idle CPU)_"
                )
                done.wait(1.0)

        def work() -> None:
            clock = threading.Thread(target=tick, name="flipviz-estimate-clock", daemon=True)
            clock.start()
            try:
                est, error = self.run.estimate_plane(), None
            except Exception as e:
                est, error = None, e
            finally:
                done.set()
                clock.join()  # its last line never lands over the result
                self.button.disabled = False
                self._busy.release()
            if error is None:
                self.show(est)
            else:
                self.text.content = f"_Cannot estimate a plane: {error}_"

        threading.Thread(target=work, name="flipviz-plane-estimate", daemon=True).start()

    def show(self, est: PlaneEstimate | None) -> None:
        """The estimate beside the plane being dragged: plane, confidence, score against azimuth."""
        self.estimate = est
        self.use_button.disabled = est is None
        self.compare_with_training()
        if est is None:
            self.text.content = HELP
            return
        n, p = est.plane.normal + 0.0, est.plane.point + 0.0
        verdict = "confident" if est.confident else "**not confident: the object may not be mirror-symmetric**"
        lines = [
            f"Normal ({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f}) through ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}); "
            f"confidence **{est.confidence:.2f}** ({verdict}; trusted from {CONFIDENT:g}), {est.seconds:.0f} s.",
        ]
        lines.append(
            "The chart: the best score of the vertical planes at each normal azimuth (about up); "
            "one sharp peak for a symmetric object."
        )
        self.text.content = " ".join(lines)
        setup = self.run.setup
        chart = score_chart(est, np.asarray(setup.up if setup is not None else WORLD_UP, dtype=np.float64))
        if self.chart is None:
            with self.folder:
                self.chart = self.server.gui.add_image(chart, label="Mirror-plane score against azimuth", format="png")
        else:
            self.chart.image = chart
