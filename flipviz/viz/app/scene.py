"""The run's 3D scene in viser: fitted sphere, planes, camera frustums, BA trajectories.

Everything of one run lives under the scene node "/run", so a restart removes it in one call.
Each group is a frame whose visibility the GUI toggles (children inherit it).
"""

from __future__ import annotations

import threading

import numpy as np
import viser

from flipviz.data.cameras import Camera
from flipviz.data.dataset import Plane
from flipviz.training.events import CameraInfo, SetupEvent
from flipviz.viz import palette
from flipviz.viz.app.poses import plane_wxyz, to_viser_pose
from flipviz.viz.images import thumbnail

# group key -> (label in the GUI, colour)
GROUPS: dict[str, tuple[str, tuple[int, int, int]]] = {
    "inputs": ("input cameras", palette.CAMERA["input"]),
    "tests": ("test cameras (unobserved)", palette.CAMERA["test"]),
    "mirrors": ("mirrored cameras (BA)", palette.CAMERA["mirror"]),
    "mirror_true": ("exact reflections", palette.CAMERA["mirror_true"]),
    "upper": ("upper-bound cameras", palette.CAMERA["upper"]),
    "trajectories": ("BA trajectories", palette.TRAJECTORY),
    "sphere": ("fitted sphere", palette.SPHERE),
    "true_plane": ("true symmetry plane", palette.TRUE_PLANE),
}
KIND_GROUP = {
    "input": "inputs",
    "test": "tests",
    "mirror_init": "mirrors",
    "mirror_true": "mirror_true",
    "upper": "upper",
}
SNAP_HIDES = ("trajectories", "sphere", "true_plane")  # groups in the way of a snapped view, hidden while it lasts
MAX_TRAJ_POINTS = 200
NESTED = 1.4  # a test frustum where a mirrored camera lands: this much larger, so the two nest


def overlaps(a: Camera, b: Camera, size: float, max_deg: float = 10.0) -> bool:
    """Two cameras' frustums of `size` would be drawn on top of each other: centres closer than the
    size and viewing directions within `max_deg`."""
    cos = float(a.c2w[:3, 2] @ b.c2w[:3, 2])
    return bool(np.linalg.norm(a.center - b.center) < size and cos > np.cos(np.radians(max_deg)))


def plane_quad(half: float) -> tuple[np.ndarray, np.ndarray]:
    """A square in the local xy plane (normal +z), as vertices and two triangles."""
    v = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]], np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def add_plane(scene: viser.SceneApi, name: str, plane: Plane, half: float, color, opacity: float = 0.25):
    """A translucent square for `plane`, centred on plane.point."""
    v, f = plane_quad(half)
    return scene.add_mesh_simple(
        name,
        v,
        f,
        color=color,
        opacity=opacity,
        side="double",
        wxyz=plane_wxyz(plane),
        position=plane.point,
        cast_shadow=False,
        receive_shadow=False,
    )


class RunScene:
    """Draws one run's cameras and geometry; moves the mirrored frustums as BA refines them."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.visible = {g: g not in ("upper", "mirror_true") for g in GROUPS}
        self.setup: SetupEvent | None = None
        self.mirror_handles: list[viser.CameraFrustumHandle] = []
        self.mirror_names: list[str] = []
        self.history: list[list[np.ndarray]] = []
        self.shown_c2w: np.ndarray | None = None  # the mirrored poses last sent (M, 4, 4)
        self.dropped: list[bool] = []  # each mirrored camera: dropped by the agreement gate (drawn grey)
        self.scale = 0.3
        self.groups: dict[str, viser.FrameHandle] = {}
        self.frustums: list[viser.CameraFrustumHandle] = []  # every camera of the run (position: its centre)
        self.hidden: list[viser.CameraFrustumHandle] = []  # hidden around a snapped view
        self._lock = threading.Lock()

    # ---- building -------------------------------------------------------------------------
    def build(self, setup: SetupEvent) -> None:
        with self._lock:
            self._clear()
            self.setup = setup
            scene = self.server.scene
            r = float(setup.sphere_radius)
            self.scale = 0.07 * r
            scene.add_frame("/run", show_axes=False)
            self.groups = {g: scene.add_frame(f"/run/{g}", show_axes=False, visible=self.visible[g]) for g in GROUPS}
            scene.add_icosphere(
                "/run/sphere/mesh",
                radius=r,
                color=GROUPS["sphere"][1],
                subdivisions=3,
                wireframe=True,
                opacity=0.12,
                position=setup.sphere_center,
                cast_shadow=False,
                receive_shadow=False,
            )
            scene.add_point_cloud(
                "/run/sphere/center",
                np.asarray(setup.sphere_center, np.float32)[None],
                (60, 90, 255),
                point_size=0.06 * r / 4.0,
                point_shape="circle",
            )
            if setup.true_plane is not None:
                add_plane(scene, "/run/true_plane/quad", setup.true_plane, 0.5 * r, GROUPS["true_plane"][1], 0.15)
            counts: dict[str, int] = {}
            mirrors = [c.camera for c in setup.cameras if c.kind == "mirror_init"] if setup.plane is not None else []
            for info in setup.cameras:
                g = KIND_GROUP.get(info.kind)
                if g is None or (g == "mirrors" and setup.plane is None):  # a method without mirrors
                    continue
                k = counts.get(g, 0)
                counts[g] = k + 1
                # a test camera where a mirrored one lands is drawn larger, around it, not doubled on its lines
                size = NESTED if g == "tests" and any(overlaps(info.camera, m, self.scale) for m in mirrors) else 1.0
                h = self._add_frustum(f"/run/{g}/{k}", info, GROUPS[g][1], with_image=g != "tests", size=size)
                self.frustums.append(h)
                if g == "mirrors":
                    self.mirror_handles.append(h)
                    self.mirror_names.append(info.camera.name)
                    self.dropped.append(False)
                    self.history.append([info.camera.center.copy()])

    def _add_frustum(self, name: str, info: CameraInfo, color, with_image: bool = True, size: float = 1.0):
        cam = info.camera
        wxyz, pos = to_viser_pose(cam.c2w)
        image = thumbnail(info.image) if (with_image and info.image is not None) else None
        return self.server.scene.add_camera_frustum(
            name,
            fov=cam.fov_y,
            aspect=cam.width / cam.height,
            scale=size * self.scale,
            color=color,
            image=image,
            wxyz=wxyz,
            position=pos,
            thickness=0.012 * self.scale / 0.3,
            cast_shadow=False,
            receive_shadow=False,
        )

    def _clear(self) -> None:
        if self.setup is not None:
            self.server.scene.remove_by_name("/run")
        self.groups = {}
        self.mirror_handles, self.mirror_names, self.history, self.shown_c2w = [], [], [], None
        self.dropped = []
        self.frustums, self.hidden = [], []
        self.setup = None

    def clear(self) -> None:
        with self._lock:
            self._clear()

    # ---- updates --------------------------------------------------------------------------
    def set_visible(self, group: str, visible: bool) -> None:
        with self._lock:
            self.visible[group] = bool(visible)
            if group in self.groups:
                self.groups[group].visible = bool(visible)

    def hide_near(self, center: np.ndarray, radius: float) -> None:
        """Hide what would lie between a snapped camera and the object: the frustums within `radius` of
        it, the BA trajectories, the sphere (the camera sits on it) and the true plane's square."""
        with self._lock:
            self._unhide()
            for h in self.frustums:
                if np.linalg.norm(np.asarray(h.position) - center) < radius and h.visible:
                    h.visible = False
                    self.hidden.append(h)
            for g in SNAP_HIDES:
                if g in self.groups:
                    self.groups[g].visible = False

    def unhide(self) -> None:
        with self._lock:
            self._unhide()

    def _unhide(self) -> None:
        for h in self.hidden:
            h.visible = True
        self.hidden = []
        for g in SNAP_HIDES:
            if g in self.groups:
                self.groups[g].visible = self.visible[g]

    def update_mirrors(self, c2w: np.ndarray) -> None:
        """Move the mirrored frustums to the refined poses (M, 4, 4) and extend their trajectories. Only
        what moved is sent: a paused or finished run sends nothing."""
        with self._lock:
            if len(c2w) != len(self.mirror_handles):
                return
            moved = np.ones(len(c2w), bool) if self.shown_c2w is None else np.any(c2w != self.shown_c2w, axis=(1, 2))
            if not moved.any():
                return
            self.shown_c2w = np.array(c2w)
            grew = False
            with self.server.atomic():
                for i in np.flatnonzero(moved):
                    T, hist = c2w[i], self.history[i]
                    self.mirror_handles[i].wxyz, self.mirror_handles[i].position = to_viser_pose(T)
                    if np.linalg.norm(T[:3, 3] - hist[-1]) > 1e-6:
                        hist.append(T[:3, 3].copy())
                        grew = True
                        if len(hist) > MAX_TRAJ_POINTS:
                            del hist[1:-1:2]  # keep the start and the end, thin out the middle
            if grew:
                self._draw_trajectories()

    def _draw_trajectories(self) -> None:
        segs = [np.stack([a, b]) for hist in self.history for a, b in zip(hist[:-1], hist[1:])]
        if not segs:
            return
        self.server.scene.add_line_segments(
            "/run/trajectories/lines",
            np.asarray(segs, np.float32),
            GROUPS["trajectories"][1],
            thickness=3.0,
            thickness_units="screen",
        )

    def set_mirror_colors(self, scores: list[float] | None) -> None:
        """Colour the mirrored frustums by their consistency PSNR on the red-yellow-green scale."""
        with self._lock:
            if scores is None or len(scores) != len(self.mirror_handles):
                return
            for h, s, gone in zip(self.mirror_handles, scores, self.dropped):
                if not gone:  # a dropped one stays grey
                    h.color = palette.score_color(s)

    def set_dropped(self, dropped_at: tuple[int | None, ...]) -> None:
        """Grey out the mirrored frustums the agreement gate dropped (StepEvent.mirror_dropped_at)."""
        with self._lock:
            if len(dropped_at) != len(self.mirror_handles):
                return
            for i, at in enumerate(dropped_at):
                if at is not None and not self.dropped[i]:
                    self.dropped[i] = True
                    self.mirror_handles[i].color = palette.DROPPED

    def set_mirror_images(self, images: list[np.ndarray]) -> None:
        """Put one image on each mirrored frustum (the flipped image, or a disagreement map)."""
        with self._lock:
            for h, img in zip(self.mirror_handles, images):
                h.image = thumbnail(img, 96)
