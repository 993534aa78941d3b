"""The Mirror tab over training: how far BA moved each mirrored camera (or its error against the
exact reflection), the refined plane's angle and offset, and the agreement gate's ratio of mirrored
to input error, pooled and each mirror's, with its limit; the gate's verdicts in words as it drops
mirrors (`MirrorCurves`); and
the refined plane in the 3D view, the trail of its normal's tip, with its motion and error in words
(`PlaneTrail`).

Built per run (one line per mirrored camera) from the run's `RunCurves`; a chart shows once it has
two points, and is sent again only when it has a new step.
"""

from __future__ import annotations

import numpy as np
import viser

from flipviz.data.dataset import Plane
from flipviz.geometry.symmetry import plane_error
from flipviz.training.events import SetupEvent
from flipviz.viz import palette
from flipviz.viz.run_curves import RunCurves

POSE_TITLES = {
    True: "Mirrored cameras: rotation error (deg) vs their exact reflections",
    False: "Mirrored cameras: rotation BA applied (deg)",
}  # no true plane: what BA moved
ONE_LINE = (
    "_The mirrored cameras' lines lie on each other: the refined plane turns every reflection alike, until BA"
    " moves each camera on its own._"
)
PLANE_TITLES = {True: "Mirror plane: error vs the true plane", False: "Mirror plane: change from its start"}
AGREE_TITLE = (
    "Mirrors vs inputs: squared error ratio on the object, all and each (judged once the NLL is on: dropped above"
    " its limit)"
)
AFTER_DROP = {  # what the run does once mirrors are dropped (--after-drop)
    "rollback": "The field went back to where the mirrors joined and trains again without {them}.",
    "restart": "Training goes on without {them}; once none is left, a fresh field trains the inputs alone, as B/L.",
    "continue": "Training goes on without {them}; what they taught the field stays.",
}


class MirrorCurves:
    """The "Over training" folder's three charts, and the gate's verdict in `verdict` (placed by the tab)."""

    def __init__(self, server: viser.ViserServer, verdict: viser.GuiMarkdownHandle) -> None:
        self.server, self.verdict = server, verdict
        self.names: list[str] = []  # the mirrored views' names (their inputs')
        self.folder = server.gui.add_folder("Over training", expand_by_default=True)
        with self.folder:
            self.one_line = server.gui.add_markdown("")  # above the charts: why the first shows one line
        self.poses: viser.GuiUplotHandle | None = None
        self.plane: viser.GuiUplotHandle | None = None
        self.agreement: viser.GuiUplotHandle | None = None
        self._plotted: tuple = ((), (), ())  # (mirror, plane, agreement) data keys of the charts shown

    def build(self, setup: SetupEvent, refining: bool) -> None:
        """This run's curves (hidden until they have points): one line per mirrored camera, and the
        plane's angle and offset when training refines it."""
        for plot in (self.poses, self.plane, self.agreement):
            if plot is not None:
                plot.remove()
        self.poses = self.plane = self.agreement = None
        self._plotted = ((), (), ())
        self.verdict.content = self.one_line.content = ""
        names = [c.source or c.camera.name for c in setup.cameras if c.kind == "mirror_init"]
        self.names = names
        if not names or setup.plane is None:
            return
        colors = [palette.hex_color(palette.series_color(i, len(names))) for i in range(len(names))]
        with self.folder:
            self.poses = self.server.gui.add_uplot(
                (np.zeros(1), *np.zeros((len(names), 1))),
                ({"label": "steps trained"}, *({"label": n, "stroke": c, "width": 1.5} for n, c in zip(names, colors))),
                title=POSE_TITLES[False],
                scales={"x": {"time": False}},
                aspect=1.6,
                legend={"show": len(names) <= 8},
                visible=False,
            )
            if refining:
                self.plane = self.server.gui.add_uplot(
                    (np.zeros(1), np.zeros(1), np.zeros(1)),
                    (
                        {"label": "steps trained"},
                        {"label": "angle (deg)", "stroke": palette.hex_color(palette.MIRROR_PLANE), "width": 2},
                        {
                            "label": "offset (units)",
                            "stroke": palette.hex_color(palette.TRUE_PLANE),
                            "width": 2,
                            "scale": "off",
                        },
                    ),
                    title=PLANE_TITLES[False],
                    scales={"x": {"time": False}, "off": {"auto": True}},
                    aspect=1.6,
                    axes=({}, {}, {"scale": "off", "side": 1, "grid": {"show": False}}),
                    visible=False,
                )
        self.agreement = self._agreement_chart(top=1.0)

    def _agreement_chart(self, top: float, order: float | None = None) -> viser.GuiUplotHandle:
        """The agreement chart, its y axis 0 to `top` (set here: uPlot's own range breaks on a leading NaN,
        and the limit must stay in view). A new top is a new chart: the browser's chart, rebuilt with
        other scales, kept a stale x range (steps 10-440 shown on [-3.7, -2.3]: no line drawn)."""
        colors = [palette.hex_color(palette.series_color(i, len(self.names))) for i in range(len(self.names))]
        with self.folder:
            return self.server.gui.add_uplot(
                (np.zeros(1), *np.zeros((3 + len(self.names), 1))),
                (
                    {"label": "steps trained"},
                    {"label": "all mirrors", "stroke": palette.hex_color(palette.CAMERA["mirror"]), "width": 3},
                    {"label": "limit (all)", "stroke": "#888888", "width": 1, "dash": [6, 4]},
                    {"label": "limit (each)", "stroke": "#bbbbbb", "width": 1, "dash": [2, 4]},
                    *({"label": n, "stroke": c, "width": 1} for n, c in zip(self.names, colors)),
                ),
                title=AGREE_TITLE,
                scales={"x": {"time": False}, "y": {"auto": False, "range": [0.0, top]}},
                aspect=1.6,
                legend={"show": len(self.names) <= 8},
                visible=False,
                order=order,
            )

    def show(self, curves: RunCurves) -> None:
        """The run's curves (RunCurves' mirror, plane and agreement data); each sent only when it has a new
        step; the gate's verdict goes in the text above the charts."""
        poses, plane, agree = curves.mirror_data(), curves.plane_data(), curves.agreement_data()
        key = tuple((len(d[0]), float(d[0][-1])) if d else () for d in (poses, plane, agree))
        if key == self._plotted:
            return
        self._plotted = key
        self.verdict.content = verdict_text(curves, self.names)
        if self.one_line.content != (note := one_line_note(poses)):
            self.one_line.content = note
        if self.agreement is not None and len(agree) >= 4 and len(agree[0]) >= 2:
            agree = (*agree, *np.full((4 + len(self.names) - len(agree), len(agree[0])), np.nan))  # pooled-only runs
            limits = [v for v in (curves.limit, curves.mirror_limit) if np.isfinite(v)]
            top = float(np.ceil(np.nanmax([*agree[1], *np.ravel(agree[4:]), *limits, 0.0]) * 1.1 + 0.01))
            if self.agreement.scales["y"]["range"][1] != top:
                old, self.agreement = self.agreement, self._agreement_chart(top, order=self.agreement.order)
                old.remove()
        for plot, data, title in (
            (self.poses, poses, POSE_TITLES[curves.mirror_vs_truth]),
            (self.plane, plane, PLANE_TITLES[curves.plane_vs_truth]),
            (self.agreement, agree, AGREE_TITLE),
        ):
            if plot is None or len(data) < 2 or len(data[0]) < 2:
                continue
            if plot.title != title:
                plot.title = title
            plot.data = data
            plot.visible = True


def one_line_note(data: tuple[np.ndarray, ...]) -> str:
    """ONE_LINE when every mirrored camera's line lies on the others (a refined plane's error turns each
    reflection by the same angle, so until BA starts they draw one line), else ""."""
    lines = np.asarray(data[1:]) if len(data) > 2 else None
    # alike within a thousandth of a degree (in float32 they come 2e-6 deg apart)
    alike = lines is not None and np.allclose(lines, lines[:1], rtol=0.0, atol=1e-3, equal_nan=True)
    return ONE_LINE if alike else ""


def verdict_text(curves: RunCurves, names: list[str]) -> str:
    """The agreement gate's verdicts in words: which mirrored views were dropped, when, how far over the
    limit, and what the run did then; "" while every one is kept."""
    gone = [(i, at) for i, at in enumerate(curves.mirror_dropped_at) if at is not None]
    if not gone and curves.dropped_at is None:
        return ""
    if not gone:  # a run that reports no per-mirror verdicts: all at once
        gone = [(i, curves.dropped_at) for i in range(len(names))]
    each = ", ".join(
        f"{names[i] if i < len(names) else i} at step {at}"
        + (f" ({curves.drop_ratio[i]:.1f}x)" if np.isfinite(curves.drop_ratio.get(i, np.nan)) else "")
        for i, at in gone
    )
    kept = len(names) - len(gone)
    them = "them" if len(gone) > 1 else "it"
    why = (
        f"Together their squared error on the object passed {curves.limit:g}x the inputs'"
        if len(gone) == len(names) and len({at for _, at in gone}) == 1
        else f"On the object each one's own squared error passed {curves.mirror_limit:g}x the inputs'"
    )
    return (
        f"**Mirrored views dropped: {each}.** {why}, so they show what the inputs contradict. "
        f"{AFTER_DROP[curves.after_drop].format(them=them)} "
        + (f"{kept} of {len(names)} mirrored views train on." if kept else "No mirrored view is left.")
    )


class PlaneTrail:
    """The plane training refines (--refine-plane): the trail of its normal's tip in the 3D view (/plane_trail)
    and, in `text`, how far it moved from where training started it and, where known, its error."""

    def __init__(self, server: viser.ViserServer, text: viser.GuiMarkdownHandle) -> None:
        self.server, self.text = server, text
        self.start: Plane | None = None  # where training started the plane
        self.true: Plane | None = None
        self.tips: list[np.ndarray] = []  # the tip of the refined plane's normal, step after step
        self.radius = 1.0

    def build(self, start: Plane, true: Plane | None, radius: float, refining: bool) -> None:
        self.start, self.true, self.tips, self.radius = start, true, [], radius
        self.text.content = (
            "_Training refines this plane: it moves with the mirrored rays' loss (orange trail)._" if refining else ""
        )

    def add(self, plane: Plane) -> bool:
        """Training moved the plane to `plane`; False (nothing sent) when the move is too small to see."""
        if self.start is None:
            return False
        tip = (plane.point + 0.4 * self.radius * plane.normal).astype(np.float32)
        if self.tips and np.linalg.norm(tip - self.tips[-1]) < 1e-3 * self.radius:
            return False
        self.tips.append(tip)
        if len(self.tips) > 1:
            segs = np.stack([np.stack(self.tips[:-1]), np.stack(self.tips[1:])], axis=1)
            self.server.scene.add_line_segments(
                "/plane_trail", segs, palette.MIRROR_PLANE, thickness=3.0, thickness_units="screen"
            )
        moved_deg, moved_off = plane_error(plane, self.start)
        text = f"**Refined plane:** turned {moved_deg:.2f}° and moved {moved_off:.3f} from where training started it"
        if self.true is not None:
            err0, err = plane_error(self.start, self.true), plane_error(plane, self.true)
            text += (
                f"; off the true plane by **{err[0]:.2f}° / {err[1]:.3f}** "
                f"(it started {err0[0]:.2f}° / {err0[1]:.3f} off)"
            )
        self.text.content = text + "."
        return True
