"""The symmetry lesson: drag the mirror plane, watch the mirrored cameras move, score the assumption.

A transform gizmo sits on the mirror plane (its local +z is the plane normal). Moving it
recomputes the initial mirrored poses live (`mirror_cameras_for_plane`, with the run's rule: each
camera reflected through the plane, or the paper's reflect-the-centre, back onto the sphere, look
at its centre) and shows them as preview frustums
carrying the flipped images. A button restarts training with that plane. The consistency score
of a mirrored view is the PSNR of the current model rendered from that camera against its
flipped image: low where the symmetry assumption fails.

The tab's other parts live apart: the preview frustums and the consistency scores
(app/mirror/scores.py: PlanePreview, MirrorScores), the estimated plane (app/estimate.py:
PlaneEstimatePanel), the charts over training with the agreement gate's verdict and the refined
plane's trail (app/mirror/curves.py: MirrorCurves, PlaneTrail).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import viser

from flipviz.data.cameras import WORLD_UP, Camera, azimuth_deg, horizontal_basis
from flipviz.data.dataset import Plane
from flipviz.geometry import flip_image, mirror_cameras_for_plane, mirror_plane
from flipviz.geometry.sphere import Sphere
from flipviz.training.events import SetupEvent
from flipviz.viz import palette
from flipviz.viz.app.estimate import PlaneEstimatePanel
from flipviz.viz.app.guard import guard_number, guard_vector
from flipviz.viz.app.mirror.curves import MirrorCurves, PlaneTrail
from flipviz.viz.app.mirror.scores import MirrorScores, PlanePreview, Scoring
from flipviz.viz.app.poses import plane_from_pose, plane_wxyz
from flipviz.viz.app.render import RenderWorker
from flipviz.viz.app.scene import RunScene, plane_quad
from flipviz.viz.run_view import RunView

LESSON = """**What the mirror assumes.** Just Flip assumes the object is *mirror-symmetric* about a
plane. Each input image is flipped left-right and given a pose: its camera reflected through the
plane (the paper: the camera centre reflected through a plane through the centre of the sphere
fitted to the cameras, put back on the sphere and aimed at its centre; the same on a ring around
the object). If the object really is symmetric, a camera there would see exactly the flipped image,
so the unobserved side gets training views for free; bundle adjustment corrects the small pose
errors and the learned variance beta^2 down-weights pixels that still disagree.

Where the object is **not** symmetric (a mug's handle, a one-sided lamp), the flipped views
contradict the real ones. Show the plane gizmo and drag it, or type a plane, to see the mirrored
cameras move (pale orange: preview); press *Score mirrors* to measure each flipped view against the
current model (red: contradicts, green: agrees); set *Mirrored frustums show* to *disagreement* to see
where; then restart training with the new plane."""

PLANE_LIMIT = 1e3  # a typed plane point or normal component (scene units)


def same_plane(a: Plane, b: Plane) -> bool:
    return bool(np.allclose(a.point, b.point) and np.allclose(a.normal, b.normal))


def plane_line(plane: Plane) -> str:
    p, n = np.round(plane.point, 2) + 0.0, np.round(plane.normal, 2) + 0.0  # + 0.0: no "-0.00"
    return f"Plane: point ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}), normal ({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f})"


class TypedPlane:
    """The "Type the plane" folder: a vertical plane by its normal's azimuth about up (through the
    sphere centre), or any plane by a point and a normal. It shows the plane in use; a plane typed
    there goes to `on_plane`, a plane that is none (a zero normal) to `on_error`."""

    def __init__(self, gui: viser.GuiApi, on_plane: Callable[[Plane], None], on_error: Callable[[str], None]) -> None:
        with gui.add_folder("Type the plane"):
            self.azimuth = guard_number(
                gui.add_slider(
                    "Vertical plane azimuth",
                    -180.0,
                    180.0,
                    1.0,
                    0.0,
                    hint="Normal (cos a, sin a, 0), through the sphere centre",
                ),
                -180.0,
                180.0,
            )
            self.point = guard_vector(gui.add_vector3("Plane point", (0.0, 0.0, 0.0), step=0.01), PLANE_LIMIT)
            self.normal = guard_vector(gui.add_vector3("Plane normal", (1.0, 0.0, 0.0), step=0.01), PLANE_LIMIT)
            apply = gui.add_button("Apply typed plane", icon=viser.Icon.CHECK)
        self.on_plane, self.on_error = on_plane, on_error
        self.shown: Plane | None = None  # the plane in use, as the fields show it
        self.up, self.center = WORLD_UP.copy(), np.zeros(3)
        self.azimuth.on_update(lambda _: self._typed_azimuth())
        apply.on_click(lambda _: self._typed_plane())

    def show(self, plane: Plane, up: np.ndarray, center: np.ndarray) -> None:
        """The fields show `plane` (the run's up and sphere centre place a typed azimuth)."""
        self.shown, self.up, self.center = plane, up, center
        self.azimuth.value = self._azimuth(plane)  # (its callback sees the plane's own azimuth: no change)
        self.point.value = tuple(round(float(x), 3) + 0.0 for x in plane.point)
        self.normal.value = tuple(round(float(x), 3) + 0.0 for x in plane.normal)

    def _azimuth(self, plane: Plane) -> float:
        """The azimuth of the plane's normal about up, in the slider's range and step."""
        return round((azimuth_deg(plane.normal, self.up) + 180.0) % 360.0 - 180.0, 1)

    def _typed_azimuth(self) -> None:
        if self.shown is None or abs(self._azimuth(self.shown) - float(self.azimuth.value)) < 0.05:
            return  # no run yet, or the field shows the plane in use: nobody typed a new azimuth
        a = np.radians(float(self.azimuth.value))
        u, v = horizontal_basis(self.up)
        self.on_plane(Plane(self.center, np.cos(a) * u + np.sin(a) * v))

    def _typed_plane(self) -> None:
        try:
            plane = Plane(np.array(self.point.value, float), np.array(self.normal.value, float))
        except ValueError as e:  # a zero normal
            self.on_error(str(e))
            return
        self.on_plane(plane)


@dataclass(frozen=True)
class RunMirrors:
    """A run's mirrors as its setup gives them: what they mirror (the inputs and their flipped images, the
    sphere, up, the initial-pose rule), the plane they start from, and what training does with them."""

    inputs: list[Camera]
    flipped: list[np.ndarray | None]
    sphere: Sphere
    up: np.ndarray
    pose: str  # the initial-pose rule: reflect | lookat
    start: Plane  # the plane training starts from (see `start_plane`)
    trains: bool  # training uses mirrored views
    dropped: bool  # a Flip run whose estimate was not confident: its mirrors dropped at setup
    refining: bool  # training moves the plane (--refine-plane)
    note: str  # what the plane shown is, for a method without mirrors

    @classmethod
    def of(cls, setup: SetupEvent) -> RunMirrors:
        inputs = [c for c in setup.cameras if c.kind == "input"]
        cams, sphere = [c.camera for c in inputs], Sphere(setup.sphere_center, setup.sphere_radius)
        start, note = start_plane(setup, cams, sphere)
        return cls(
            inputs=cams,
            flipped=[flip_image(c.image) if c.image is not None else None for c in inputs],
            sphere=sphere,
            up=np.asarray(setup.up, dtype=np.float64),
            pose=setup.cfg.flip.mirror_pose,
            start=start,
            trains=setup.plane is not None,
            dropped=setup.plane is None and setup.plane_estimate is not None,
            refining=setup.plane is not None and setup.cfg.flip.refine_plane,
            note=note,
        )

    def cameras(self, plane: Plane) -> list[Camera]:
        """The initial mirrored cameras for `plane`, by the run's rule."""
        return mirror_cameras_for_plane(self.inputs, plane, self.sphere, self.up, self.pose)


def start_plane(setup: SetupEvent, inputs: list[Camera], sphere: Sphere) -> tuple[Plane, str]:
    """The plane the run trains with; a doubted estimate's; else the plane a Flip run would start from,
    with what it is."""
    if setup.plane is not None:
        return setup.plane, ""
    if setup.plane_estimate is not None:  # estimated, dropped: not confident
        return setup.plane_estimate.plane, ""
    preset = setup.cfg.flip.mirror_plane  # a method without mirrors
    try:
        return mirror_plane(preset, inputs, sphere, setup.true_plane), (
            "this is the plane a Flip run with these settings starts from."
        )
    except Exception:  # auto: only an estimate knows it
        return mirror_plane("opposite", inputs, sphere), (
            f"a Flip run would estimate its plane (`--mirror-plane {preset}`: *Estimate "
            "plane* below); this one only faces away from the inputs (`opposite`)."
        )


class MirrorLesson:
    """The Mirror tab: a plane gizmo and its square, the preview of the mirrors a plane gives, restart with
    a plane; the tab's other parts are built here and kept apart (scores, charts, trail, estimate)."""

    def __init__(
        self,
        server: viser.ViserServer,
        worker: RenderWorker,
        run: RunView,
        scene: RunScene,
        on_restart: Callable[[Plane], None],
    ) -> None:
        self.server, self.run, self.on_restart = server, run, on_restart
        gui = server.gui
        gui.add_markdown(LESSON)
        self.plane_text = gui.add_markdown("_No run yet._")
        self.trail = PlaneTrail(server, gui.add_markdown(""))  # the plane as training refines it (--refine-plane)
        gate_text = gui.add_markdown("")  # the agreement gate's verdict (training/flip.py: Agreement)
        self.show_gizmo = gui.add_checkbox(
            "Show plane gizmo", False, hint="Drag its arrows and rings to move the plane"
        )
        self.show_preview = gui.add_checkbox("Show plane preview", True)
        self.show_plane = gui.add_checkbox("Show mirror plane", True, hint="The translucent square of the plane")
        self.typed = TypedPlane(gui, on_plane=self.set_plane, on_error=self._cannot)
        reset_btn = gui.add_button("Reset plane", icon=viser.Icon.REFRESH)
        restart_btn = gui.add_button("Restart with this plane", icon=viser.Icon.FLIP_VERTICAL, color="orange")
        # the parts kept apart: app/mirror/scores.py, app/mirror/curves.py, app/estimate.py
        self.consistency = MirrorScores(gui, worker, run, scene, self.show_anyway, self._scoring)
        self.curves = MirrorCurves(server, verdict=gate_text)  # charts over training
        self.estimate = PlaneEstimatePanel(server, run, lambda: self.train_plane, self.set_plane)
        self.preview = PlanePreview(server)
        reset_btn.on_click(lambda _: self.reset_plane())
        restart_btn.on_click(lambda _: self.restart())
        self.show_preview.on_update(lambda _: self._set_preview_visible())
        self.show_gizmo.on_update(lambda _: self._set_gizmo_visible())
        self.show_plane.on_update(lambda _: self._set_gizmo_visible())
        self._lock = threading.Lock()
        self.mirrors: RunMirrors | None = None  # the run's mirrors (None before a run)
        # the plane: the one training uses now, the one shown (moved by you or following training)
        self.train_plane: Plane | None = None
        self.plane: Plane | None = None
        self.gizmo: viser.TransformControlsHandle | None = None
        self.quad: viser.MeshHandle | None = None  # the mirror plane's square, drawn apart from its gizmo
        self.moved = False  # you moved the plane: the gizmo no longer follows training
        self.snapped = False  # a browser is at a snapped view: the square would wash over it
        self.anyway = False  # the dropped mirrors are drawn and scored, though training ignores them
        self.dropped_at: tuple[int | None, ...] = ()  # each mirror: the step the agreement gate dropped it at

    # ---- per run ----------------------------------------------------------------------------
    def build(self, setup: SetupEvent) -> None:
        with self._lock:
            self.mirrors = m = RunMirrors.of(setup)
            plane = self.train_plane = m.start
            r = float(setup.sphere_radius)
            self.trail.build(plane, setup.true_plane, r, m.refining)
            scene = self.server.scene
            self.gizmo = scene.add_transform_controls(
                "/plane",
                scale=0.6 * r,
                line_width=6.0,
                wxyz=plane_wxyz(plane),
                position=plane.point,
                opacity=0.9,
                visible=bool(self.show_gizmo.value),
            )
            v, f = plane_quad(0.55 * r)
            self.quad = scene.add_mesh_simple(
                "/mirror_plane",
                v,
                f,
                color=palette.MIRROR_PLANE,
                opacity=0.18,
                side="double",
                cast_shadow=False,
                receive_shadow=False,
                wxyz=plane_wxyz(plane),
                position=plane.point,
                visible=bool(self.show_plane.value) and not self.snapped,
            )
            self.preview.clear()
            self.anyway, self.dropped_at = False, ()
            self.consistency.anyway_btn.visible = m.dropped
            self.moved = False
            self.gizmo.on_update(self._on_gizmo)
            self._apply_plane(plane)
        self.consistency.clear()
        self.estimate.show(setup.plane_estimate)
        self.curves.build(setup, m.refining)

    def clear(self) -> None:
        with self._lock:
            if self.gizmo is not None:
                for name in ("/plane", "/mirror_plane", "/preview", "/plane_trail"):
                    self.server.scene.remove_by_name(name)
            self.gizmo, self.quad = None, None
            self.preview.clear()

    # ---- the plane --------------------------------------------------------------------------
    def _on_gizmo(self, ev: viser.TransformControlsEvent) -> None:
        if ev.phase == "start":
            return
        self.moved = True
        self._apply_plane(plane_from_pose(ev.target.wxyz, ev.target.position))

    def _set_gizmo_visible(self) -> None:
        if self.gizmo is not None:
            self.gizmo.visible = bool(self.show_gizmo.value)
        if self.quad is not None:
            self.quad.visible = bool(self.show_plane.value) and not self.snapped

    def set_snapped(self, snapped: bool) -> None:
        """Hide the plane's square while a browser is at a snapped view (its gizmo stays, if asked for)."""
        self.snapped = snapped
        self._set_gizmo_visible()

    def _cannot(self, why: str) -> None:
        self.plane_text.content = f"_Cannot use that plane: {why}._"

    def set_plane(self, plane: Plane) -> None:
        """Move the gizmo (as if dragged) to `plane`."""
        if self.gizmo is None:
            return
        self.gizmo.wxyz, self.gizmo.position = plane_wxyz(plane), plane.point
        self.moved = True
        self._apply_plane(plane)

    def follow_training(self, plane: Plane) -> None:
        """Training moved the plane (--refine-plane): the square and, unless you moved it, the gizmo follow;
        the trail grows and says how far it moved and, where known, its error."""
        with self._lock:
            if self.mirrors is None or not self.trail.add(plane):
                return  # no run, or no visible change: nothing sent
            self.train_plane = plane  # Reset plane goes back to the plane training uses now
            if self.quad is not None:
                self.quad.wxyz, self.quad.position = plane_wxyz(plane), plane.point
            if self.gizmo is not None and not self.moved:  # the gizmo, the typed fields and the plane in use follow
                self.plane = plane
                self.gizmo.wxyz, self.gizmo.position = plane_wxyz(plane), plane.point
                self.typed.show(plane, self.mirrors.up, self.mirrors.sphere.center)
                self.plane_text.content = plane_line(plane) + " - the plane training uses now."
            self.estimate.compare_with_training(self.run.step)

    def reset_plane(self) -> None:
        if self.train_plane is not None and self.gizmo is not None:
            self.gizmo.wxyz, self.gizmo.position = plane_wxyz(self.train_plane), self.train_plane.point
            self.moved = False
            self._apply_plane(self.train_plane)

    def _apply_plane(self, plane: Plane) -> None:
        """Recompute the initial mirrored poses for `plane` and move the preview frustums."""
        m = self.mirrors
        if m is None or not m.inputs:
            return
        try:
            cams = m.cameras(plane)
        except Exception as e:  # e.g. a reflected centre at the sphere centre
            self.plane_text.content = f"_Cannot mirror with this plane: {e}_"
            return
        moved = self.plane is None or not same_plane(self.plane, plane)
        self.plane = plane
        if self.quad is not None:
            self.quad.wxyz, self.quad.position = plane_wxyz(plane), plane.point
        self.preview.show(cams, m.inputs, m.flipped, float(m.sphere.radius), self._preview_wanted(), moved)
        self._set_preview_visible()
        self.typed.show(plane, m.up, m.sphere.center)
        self.plane_text.content = plane_line(plane) + self._plane_note(plane)

    def _plane_note(self, plane: Plane) -> str:
        """What the plane shown is to this run."""
        m = self.mirrors
        if not m.trains and m.dropped:
            return (
                " - the estimate is **not confident**, so this run trains on **no** mirrored view "
                "(`--unconfident-plane use` keeps them). *Show the mirrors anyway* draws and scores them."
            )
        if not m.trains:
            return " - this method trains on **no** mirrored view; " + m.note
        if self.train_plane is None or not same_plane(plane, self.train_plane):
            return " - **moved**: restart to train with it."
        return " - where training started the plane." if m.refining else " - the training plane."

    def _preview_wanted(self) -> bool:
        return bool(self.show_preview.value and (self.moved or self._doubted_shown()))

    def _doubted_shown(self) -> bool:
        """The mirrors an unconfident estimate dropped at setup are shown anyway (as the plane's preview)."""
        return self.anyway and self.mirrors is not None and self.mirrors.dropped

    def on_dropped(self, dropped_at: tuple[int | None, ...]) -> None:
        """The agreement gate dropped mirrors in training (StepEvent.mirror_dropped_at): they stay drawn
        (grey), and *Show the mirrors anyway* shows what each one's flipped image contradicts."""
        if any(at is not None for at in dropped_at):
            self.dropped_at = tuple(dropped_at)
            self.consistency.anyway_btn.visible = True

    def show_anyway(self) -> None:
        """The lesson of an asymmetric object in one click: the mirrors that were dropped (by an unconfident
        estimate: drawn at the estimated plane's poses; by the agreement gate: where BA left them), scored,
        showing their disagreement maps: where the flipped images show what no input saw."""
        self.anyway = True
        self.consistency.frustum_shows.value = "disagreement"
        self._set_preview_visible()
        self.consistency.request()

    def _set_preview_visible(self) -> None:
        self.preview.set_visible(self._preview_wanted())

    def restart(self) -> None:
        if self.plane is not None:
            self.on_restart(self.plane)

    def _scoring(self) -> Scoring:
        """What *Score mirrors* scores: the preview's cameras (the plane moved, or a doubted plane's
        mirrors shown anyway), else the mirrored cameras training uses now (BA's poses)."""
        m = self.mirrors
        if m is None:  # no run yet: nothing to score
            return Scoring([], [], [], "no run yet", None)
        at = self.dropped_at if len(self.dropped_at) == len(m.inputs) else (None,) * len(m.inputs)
        names = [f"{c.name}_flip" + (f" (dropped at {s})" if s is not None else "") for c, s in zip(m.inputs, at)]
        if (self.moved or self._doubted_shown()) and self.preview.cams:
            what = "plane preview" if self.moved else "doubted plane, not trained on"
            return Scoring(self.preview.cams, m.flipped, names, f"{what}, step {self.run.step}", self.preview)
        c2w = self.run.mirror_c2w
        if c2w is None or len(c2w) != len(m.inputs):
            cams = m.cameras(self.train_plane)
        else:
            cams = [c.with_pose(T) for c, T in zip(m.inputs, c2w)]
        return Scoring(cams, m.flipped, names, f"BA poses, step {self.run.step}", None)  # (training's label)
