"""The symmetry lesson: drag the mirror plane, watch the mirrored cameras move, score the assumption.

A transform gizmo sits on the mirror plane (its local +z is the plane normal). Moving it
recomputes the initial mirrored poses live (`mirror_cameras_for_plane`, with the run's rule: each
camera reflected through the plane, or the paper's reflect-the-centre, back onto the sphere, look
at its centre) and shows them as preview frustums
carrying the flipped images. A button restarts training with that plane. The consistency score
of a mirrored view is the PSNR of the current model rendered from that camera against its
flipped image: low where the symmetry assumption fails.

The tab's other parts live apart: the estimated plane (viser_estimate.py: PlaneEstimatePanel) and
the charts over training with the agreement gate's verdict (viser_mirror_curves.py: MirrorCurves).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import viser

from flipviz.data.cameras import WORLD_UP, Camera, azimuth_deg, horizontal_basis
from flipviz.data.dataset import Plane
from flipviz.data.images import to_uint8
from flipviz.geometry import flip_image, mirror_cameras_for_plane, mirror_plane
from flipviz.geometry.sphere import Sphere
from flipviz.geometry.symmetry import plane_error
from flipviz.training.evaluate import image_psnr
from flipviz.training.events import ImagesEvent, SetupEvent
from flipviz.viz import palette
from flipviz.viz.run_view import RunView
from flipviz.viz.viser_common import (
    error_map,
    plane_from_pose,
    plane_wxyz,
    resize_nearest,
    thumbnail,
    to_viser_pose,
)
from flipviz.viz.viser_estimate import PlaneEstimatePanel
from flipviz.viz.viser_guard import guard_choice, guard_number, guard_vector
from flipviz.viz.viser_mirror_curves import MirrorCurves
from flipviz.viz.viser_render import RenderWorker
from flipviz.viz.viser_scene import RunScene, plane_quad

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

FRUSTUM_IMAGES = ("flipped image", "disagreement", "beta^2")
PLANE_LIMIT = 1e3  # a typed plane point or normal component (scene units)


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


class MirrorLesson:
    """The Mirror tab: a plane gizmo, live preview frustums, consistency scores, restart with a plane."""

    def __init__(
        self,
        server: viser.ViserServer,
        worker: RenderWorker,
        run: RunView,
        scene: RunScene,
        on_restart: Callable[[Plane], None],
    ) -> None:
        self.server, self.worker, self.run, self.scene, self.on_restart = server, worker, run, scene, on_restart
        gui = server.gui
        gui.add_markdown(LESSON)
        self.plane_text = gui.add_markdown("_No run yet._")
        self.refine_text = gui.add_markdown("")  # the plane as training refines it (--refine-plane)
        gate_text = gui.add_markdown("")  # the agreement gate's verdict (training/flip.py: Agreement)
        self.show_gizmo = gui.add_checkbox(
            "Show plane gizmo", False, hint="Drag its arrows and rings to move the plane"
        )
        self.show_preview = gui.add_checkbox("Show plane preview", True)
        self.show_plane = gui.add_checkbox("Show mirror plane", True, hint="The translucent square of the plane")
        self.typed = TypedPlane(gui, on_plane=self.set_plane, on_error=self._cannot)
        self.frustum_shows = guard_choice(
            gui.add_dropdown(
                "Mirrored frustums show",
                FRUSTUM_IMAGES,
                initial_value=FRUSTUM_IMAGES[0],
                hint="disagreement: |flipped image - the model seen from the mirrored camera|",
            ),
            FRUSTUM_IMAGES,
        )
        self.anyway_btn = gui.add_button(
            "Show the mirrors anyway (not trained on)",
            icon=viser.Icon.EYE,
            visible=False,
            hint="The doubted plane's mirrored cameras, scored and showing where their flipped images disagree",
        )  # shown when an unconfident estimate dropped the mirrors
        self.score_btn = gui.add_button("Score mirrors", icon=viser.Icon.RULER, hint="Render each mirrored view now")
        self.reset_btn = gui.add_button("Reset plane", icon=viser.Icon.REFRESH)
        self.restart_btn = gui.add_button("Restart with this plane", icon=viser.Icon.FLIP_VERTICAL, color="orange")
        self.table = gui.add_markdown("_Scores appear with the first image event or Score mirrors._")
        self.curves = MirrorCurves(server, verdict=gate_text)  # charts over training (viser_mirror_curves.py)
        self.estimate = PlaneEstimatePanel(server, run, lambda: self.train_plane, self.set_plane)  # viser_estimate.py
        self.up, self.pose = WORLD_UP.copy(), "reflect"  # the run's up and initial-pose rule
        self.inputs: list[Camera] = []
        self.flipped: list[np.ndarray] = []
        self.sphere: Sphere | None = None
        self.train_plane: Plane | None = None
        self.plane: Plane | None = None
        self.gizmo: viser.TransformControlsHandle | None = None
        self.preview: list[viser.CameraFrustumHandle] = []
        self.preview_frame: viser.FrameHandle | None = None
        self.preview_cams: list[Camera] = []
        self.moved = False
        self.scores: dict[str, list[float]] = {}
        self._lock = threading.Lock()
        self.score_btn.on_click(lambda _: self.worker.submit("mirror-score", self._score_now, priority=0))
        self.anyway_btn.on_click(lambda _: self.show_anyway())
        self.reset_btn.on_click(lambda _: self.reset_plane())
        self.restart_btn.on_click(lambda _: self.restart())
        self.show_preview.on_update(lambda _: self._set_preview_visible())
        self.show_gizmo.on_update(lambda _: self._set_gizmo_visible())
        self.show_plane.on_update(lambda _: self._set_gizmo_visible())
        self.frustum_shows.on_update(lambda _: self._show_frustum_images())
        self.last_images: ImagesEvent | None = None
        self.quad: viser.MeshHandle | None = None  # the mirror plane, drawn apart from its gizmo
        self.snapped = False  # a browser is at a snapped view: the square would wash over it
        self.start_plane: Plane | None = None  # where training started the plane (it may move: --refine-plane)
        self.true_plane: Plane | None = None
        self.trail: list[np.ndarray] = []  # the tip of the refined plane's normal, step after step
        self.refining = False  # this run's training moves the plane
        self.trains_mirrors, self.dropped = True, False
        self.anyway = False  # the dropped mirrors are drawn and scored, though training ignores them
        self.no_mirror_note = ""  # what the plane shown for a method without mirrors is

    # ---- per run ----------------------------------------------------------------------------
    def build(self, setup: SetupEvent) -> None:
        with self._lock:
            inputs = [c for c in setup.cameras if c.kind == "input"]
            self.inputs = [c.camera for c in inputs]
            self.flipped = [flip_image(c.image) if c.image is not None else None for c in inputs]
            self.sphere = Sphere(setup.sphere_center, setup.sphere_radius)
            self.up = np.asarray(setup.up, dtype=np.float64)
            self.pose = str(setup.settings.get("mirror_pose", "reflect"))
            plane = setup.plane
            if plane is None and setup.plane_estimate is not None:  # estimated, dropped: not confident
                plane = setup.plane_estimate.plane
            elif plane is None:  # a method without mirrors: the plane a Flip run would start from, where known
                preset = str(setup.settings.get("mirror_plane", "official"))
                try:
                    plane = mirror_plane(preset, self.inputs, self.sphere, setup.true_plane)
                    self.no_mirror_note = "this is the plane a Flip run with these settings starts from."
                except Exception:  # auto: only an estimate knows it
                    plane = mirror_plane("opposite", self.inputs, self.sphere)
                    self.no_mirror_note = (
                        f"a Flip run would estimate its plane (`--mirror-plane {preset}`: *Estimate "
                        "plane* below); this one only faces away from the inputs (`opposite`)."
                    )
            self.train_plane = self.start_plane = plane
            self.true_plane, self.trail = setup.true_plane, []
            self.refining = setup.plane is not None and bool(setup.settings.get("refine_plane"))
            self.refine_text.content = (
                "_Training refines this plane: it moves with the mirrored rays' loss (orange trail)._"
                if self.refining
                else ""
            )
            self.scores = {}
            r = float(setup.sphere_radius)
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
            self.preview, self.preview_frame = [], None
            self.trains_mirrors = setup.plane is not None
            self.dropped = setup.plane is None and setup.plane_estimate is not None  # a Flip run, plane not confident
            self.anyway = False
            self.anyway_btn.visible = self.dropped
            self.moved = False
            self.gizmo.on_update(self._on_gizmo)
            self._apply_plane(plane)
        self.table.content = "_Scores appear with the first image event or Score mirrors._"
        self.estimate.show(setup.plane_estimate)
        self.curves.build(setup, self.refining)

    def clear(self) -> None:
        with self._lock:
            if self.gizmo is not None:
                for name in ("/plane", "/mirror_plane", "/preview", "/plane_trail"):
                    self.server.scene.remove_by_name(name)
            self.gizmo, self.preview, self.preview_cams, self.preview_frame, self.quad = None, [], [], None, None

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
        """Training moved the plane (--refine-plane): the quad and, unless you moved it, the gizmo follow;
        the trail of its normal's tip grows; the text says how far it moved and, where known, its error."""
        with self._lock:
            if self.start_plane is None or self.sphere is None:
                return
            r = float(self.sphere.radius)
            tip = (plane.point + 0.4 * r * plane.normal).astype(np.float32)
            if self.trail and np.linalg.norm(tip - self.trail[-1]) < 1e-3 * r:
                return  # no visible change: nothing sent
            self.trail.append(tip)
            self.train_plane = plane  # Reset plane goes back to the plane training uses now
            if self.quad is not None:
                self.quad.wxyz, self.quad.position = plane_wxyz(plane), plane.point
            if self.gizmo is not None and not self.moved:  # the gizmo, the typed fields and the plane in use follow
                self.plane = plane
                self.gizmo.wxyz, self.gizmo.position = plane_wxyz(plane), plane.point
                self.typed.show(plane, self.up, self.sphere.center)
                self.plane_text.content = plane_line(plane) + " - the plane training uses now."
            if len(self.trail) > 1:
                segs = np.stack([np.stack(self.trail[:-1]), np.stack(self.trail[1:])], axis=1)
                self.server.scene.add_line_segments(
                    "/plane_trail", segs, palette.MIRROR_PLANE, thickness=3.0, thickness_units="screen"
                )
            moved_deg, moved_off = plane_error(plane, self.start_plane)
            text = (
                f"**Refined plane:** turned {moved_deg:.2f}° and moved {moved_off:.3f} from where training started it"
            )
            if self.true_plane is not None:
                err0, err = plane_error(self.start_plane, self.true_plane), plane_error(plane, self.true_plane)
                text += (
                    f"; off the true plane by **{err[0]:.2f}° / {err[1]:.3f}** "
                    f"(it started {err0[0]:.2f}° / {err0[1]:.3f} off)"
                )
            self.refine_text.content = text + "."

    def reset_plane(self) -> None:
        if self.train_plane is not None and self.gizmo is not None:
            self.gizmo.wxyz, self.gizmo.position = plane_wxyz(self.train_plane), self.train_plane.point
            self.moved = False
            self._apply_plane(self.train_plane)

    def _apply_plane(self, plane: Plane) -> None:
        """Recompute the initial mirrored poses for `plane` and move the preview frustums."""
        if self.sphere is None or not self.inputs:
            return
        try:
            cams = mirror_cameras_for_plane(self.inputs, plane, self.sphere, self.up, self.pose)
        except Exception as e:  # e.g. a reflected centre at the sphere centre
            self.plane_text.content = f"_Cannot mirror with this plane: {e}_"
            return
        old = self.plane
        moved = old is None or not (np.allclose(old.point, plane.point) and np.allclose(old.normal, plane.normal))
        self.plane, self.preview_cams = plane, cams
        scene = self.server.scene
        if self.quad is not None:
            self.quad.wxyz, self.quad.position = plane_wxyz(plane), plane.point
        r = float(self.sphere.radius)
        with self.server.atomic():
            if not self.preview:
                self.preview_frame = scene.add_frame("/preview", show_axes=False, visible=self._preview_wanted())
                for k, (cam, img) in enumerate(zip(cams, self.flipped)):
                    wxyz, pos = to_viser_pose(cam.c2w)
                    self.preview.append(
                        scene.add_camera_frustum(
                            f"/preview/{k}",
                            fov=cam.fov_y,
                            aspect=cam.width / cam.height,
                            scale=0.07 * r,
                            color=palette.CAMERA["mirror_init"],
                            image=thumbnail(img) if img is not None else None,
                            wxyz=wxyz,
                            position=pos,
                            thickness=0.01 * r / 4.0,
                            cast_shadow=False,
                            receive_shadow=False,
                        )
                    )
            else:
                for h, cam in zip(self.preview, cams):
                    h.wxyz, h.position = to_viser_pose(cam.c2w)
            links = np.stack([np.stack([a.center, b.center]) for a, b in zip(self.inputs, cams)]).astype(np.float32)
            scene.add_line_segments(
                "/preview/links", links, palette.CAMERA["mirror_init"], thickness=1.5, thickness_units="screen"
            )
            if moved:
                for h in self.preview:
                    h.color = palette.CAMERA["mirror_init"]  # not scored for this plane yet
        self._set_preview_visible()
        self.typed.show(plane, self.up, self.sphere.center)
        same = (
            self.train_plane is not None
            and np.allclose(plane.point, self.train_plane.point)
            and np.allclose(plane.normal, self.train_plane.normal)
        )
        where = plane_line(plane)
        if not self.trains_mirrors and self.dropped:
            self.plane_text.content = where + (
                " - the estimate is **not confident**, so this run trains on **no** mirrored view "
                "(`--unconfident-plane use` keeps them). *Show the mirrors anyway* draws and scores them."
            )
        elif not self.trains_mirrors:
            self.plane_text.content = where + (" - this method trains on **no** mirrored view; " + self.no_mirror_note)
        else:
            trained = " - where training started the plane." if self.refining else " - the training plane."
            self.plane_text.content = where + (trained if same else " - **moved**: restart to train with it.")

    def _preview_wanted(self) -> bool:
        return bool(self.show_preview.value and (self.moved or self.anyway))

    def show_anyway(self) -> None:
        """The lesson of an asymmetric object in one click: the mirrors an unconfident estimate dropped,
        drawn at the estimated plane's poses, coloured by their scores, showing their disagreement maps."""
        self.anyway = True
        self.frustum_shows.value = "disagreement"
        self._set_preview_visible()
        self.worker.submit("mirror-score", self._score_now, priority=0)

    def _set_preview_visible(self) -> None:
        if self.preview_frame is not None:
            self.preview_frame.visible = self._preview_wanted()

    def restart(self) -> None:
        if self.plane is not None:
            self.on_restart(self.plane)

    # ---- consistency scores -----------------------------------------------------------------
    def on_images(self, event: ImagesEvent) -> None:
        """PSNR of the model rendered from each (BA-refined) mirrored camera vs its flipped image."""
        if event.mirror_views:
            s = [image_psnr(v.rgb, v.gt) if v.gt is not None else float("nan") for v in event.mirror_views]
            self.scores[f"BA poses, step {event.step}"] = s
            self.scene.set_mirror_colors(s)
            self.last_images = event
            self._show_frustum_images()
            self._show_table([v.name for v in event.mirror_views])

    def _show_frustum_images(self) -> None:
        """The mirrored frustums' images: the flipped image, its disagreement with the model, or beta^2."""
        ev, which = self.last_images, self.frustum_shows.value
        if ev is None or not ev.mirror_views:
            return
        if which == "disagreement":
            imgs = [error_map(v.rgb, v.gt) for v in ev.mirror_views if v.gt is not None]
        elif which == "beta^2" and ev.mirror_views[0].beta2 is not None:
            imgs = [palette.colormap(v.beta2, *palette.BETA2_RANGE) for v in ev.mirror_views]
        else:
            imgs = [to_uint8(v.gt) for v in ev.mirror_views if v.gt is not None]
        self.scene.set_mirror_images(imgs)

    def _score_now(self) -> None:
        """Render from the preview poses (plane moved) or the current BA poses, and score them."""
        preview = (self.moved or self.anyway) and bool(self.preview_cams)
        if preview:
            what = "plane preview" if self.moved else "doubted plane, not trained on"
            cams, label = self.preview_cams, f"{what}, step {self.run.step}"
        else:
            c2w = self.run.mirror_c2w
            if c2w is None or len(c2w) != len(self.inputs):
                cams = mirror_cameras_for_plane(self.inputs, self.train_plane, self.sphere, self.up, self.pose)
            else:
                cams = [c.with_pose(T) for c, T in zip(self.inputs, c2w)]
            label = f"BA poses (now), step {self.run.step}"
        scores, disagreement = [], []
        for cam, gt in zip(cams, self.flipped):
            out = self.run.render(cam, outputs=("rgb",))
            if out is None or gt is None:
                scores.append(float("nan"))
                disagreement.append(None)
                continue
            rgb, gt = out["rgb"], resize_nearest(gt, out["rgb"].shape[1], out["rgb"].shape[0])
            scores.append(image_psnr(rgb, gt))
            disagreement.append(error_map(rgb, gt))
        if not preview:
            self.scene.set_mirror_colors(scores)
        else:  # the preview frustums take the colours of their scores (and, asked for, the disagreement maps)
            show_maps = self.frustum_shows.value == "disagreement"
            for h, sc, img, flipped in zip(self.preview, scores, disagreement, self.flipped):
                h.color = palette.score_color(sc)
                if flipped is not None:
                    h.image = thumbnail(img if show_maps and img is not None else flipped)
        self.scores[label] = scores  # published once the frustums wear them
        self._show_table([f"{c.name}_flip" for c in self.inputs])

    def _show_table(self, names: list[str]) -> None:
        cols = list(self.scores)[-3:]  # the latest three scorings
        head = "| mirrored view | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols) + "\n"
        rows = []
        for i, n in enumerate(names):
            cells = [f"{self.scores[c][i]:.1f} dB" if i < len(self.scores[c]) else "" for c in cols]
            rows.append(f"| {n} | " + " | ".join(cells) + " |")
        means = [np.nanmean(self.scores[c]) if len(self.scores[c]) else float("nan") for c in cols]
        rows.append("| **mean** | " + " | ".join(f"**{m:.1f} dB**" for m in means) + " |")
        lo, hi = palette.SCORE_RANGE
        self.table.content = (
            "Consistency = PSNR of the model seen from each mirrored camera vs its flipped image "
            f"(low = the symmetry assumption fails there). Frustum colours: red {lo:g} dB or less (contradicts), "
            f"yellow {0.5 * (lo + hi):g} dB, green {hi:g} dB or more (agrees).\n\n" + head + "\n".join(rows)
        )
