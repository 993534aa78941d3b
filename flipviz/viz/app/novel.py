"""Novel cameras (draggable gizmos you render the model from) and 'snap to view k'."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import viser

from flipviz.data.cameras import Camera, look_at
from flipviz.data.images import to_uint8
from flipviz.training.evaluate import image_psnr, structure_scores
from flipviz.viz import palette
from flipviz.viz.app.guard import guard_choice
from flipviz.viz.app.poses import camera_from_viser, to_viser_pose
from flipviz.viz.app.render import RenderWorker
from flipviz.viz.images import OUTPUTS, error_map, upscale, visualize_output
from flipviz.viz.run_view import RunView

BLANK = np.full((48, 48, 3), 235, np.uint8)  # placeholder until the first render
MAX_NOVEL = 16  # novel cameras at once (shared by all clients)


class NovelCameras:
    """Draggable cameras (transform gizmo + frustum) and a Render button; shared by all clients."""

    def __init__(self, server: viser.ViserServer, worker: RenderWorker, run: RunView) -> None:
        self.server, self.worker, self.run = server, worker, run
        self.gizmos: dict[str, viser.TransformControlsHandle] = {}
        self._count = 0
        self.frustums: dict[str, viser.CameraFrustumHandle] = {}
        self._lock = threading.Lock()
        gui = server.gui
        self.add_btn = gui.add_button("Add novel camera", icon=viser.Icon.CAMERA_PLUS, hint="At your current view")
        self.select = gui.add_dropdown("Novel camera", ("(none)",))
        self.output = guard_choice(gui.add_dropdown("Novel output", OUTPUTS, initial_value="RGB"), OUTPUTS)
        self.render_btn = gui.add_button("Render novel view", icon=viser.Icon.PHOTO)
        self.delete_btn = gui.add_button("Delete camera", icon=viser.Icon.TRASH, hint="Remove the selected camera")
        self.image = gui.add_image(BLANK, label="Novel render", format="jpeg")
        self.status = gui.add_markdown("_Add a camera, drag its gizmo, press Render._")
        self.add_btn.on_click(lambda ev: self.add(ev.client))
        self.render_btn.on_click(lambda _: self.request(self.select.value, priority=0))
        self.output.on_update(lambda _: self.request(self.select.value, priority=0))
        self.delete_btn.on_click(lambda _: self.delete(self.select.value))

    def add(self, client: viser.ClientHandle | None = None) -> str:
        """Add a novel camera at `client`'s current view (or looking at the sphere centre)."""
        setup = self.run.setup
        with self._lock:
            if len(self.gizmos) >= MAX_NOVEL:  # each is rendered on request: a client cannot pile them up
                self.status.content = f"_At most {MAX_NOVEL} novel cameras: delete one first._"
                return ""
            self._count += 1
            name = f"cam{self._count}"
            if client is not None:
                try:  # your view, a third of the way to what you look at (so that you see the gizmo)
                    wxyz, pos = client.camera.wxyz.copy(), client.camera.position.copy()
                    pos = pos + (client.camera.look_at - pos) / 3.0
                except AssertionError:
                    client = None
            if client is None:
                center = setup.sphere_center if setup is not None else np.zeros(3)
                r = setup.sphere_radius if setup is not None else 4.0
                c = center + r * np.array([0.6, -0.6, 0.5]) / np.linalg.norm([0.6, -0.6, 0.5])
                wxyz, pos = to_viser_pose(look_at(c, center))
            scale = 0.15 * (setup.sphere_radius if setup is not None else 4.0)
            g = self.server.scene.add_transform_controls(f"/novel/{name}", scale=scale, wxyz=wxyz, position=pos)
            fov, aspect = self._fov_aspect()
            f = self.server.scene.add_camera_frustum(
                f"/novel/{name}/frustum",
                fov=fov,
                aspect=aspect,
                scale=0.6 * scale,
                color=palette.CAMERA["novel"],
                thickness=0.02 * scale,
                cast_shadow=False,
                receive_shadow=False,
            )
            self.gizmos[name], self.frustums[name] = g, f
            self.select.options = tuple(self.gizmos)
            self.select.value = name

        @g.on_update
        def _(ev: viser.TransformControlsEvent) -> None:
            if ev.phase == "end":
                self.request(name, priority=1)

        return name

    def delete(self, name: str) -> None:
        """Remove a novel camera (its gizmo and frustum)."""
        with self._lock:
            if name not in self.gizmos:
                return
            self.worker.cancel(lambda k: k == ("novel", name))
            self.server.scene.remove_by_name(f"/novel/{name}")
            del self.gizmos[name], self.frustums[name]
            self.select.options = tuple(self.gizmos) or ("(none)",)
            self.select.value = self.select.options[-1]
        self.image.image = BLANK
        self.status.content = f"_Deleted `{name}`._"

    def reset(self) -> None:
        """A new run: the cameras stay where they are, their renders belong to the old run."""
        self.image.image = BLANK
        for f in self.frustums.values():
            f.image = None
        self.status.content = "_New run: press Render for its view._"

    def _input_camera(self) -> Camera | None:
        setup = self.run.setup
        return next((c.camera for c in setup.cameras if c.kind == "input"), None) if setup is not None else None

    def _fov_aspect(self) -> tuple[float, float]:
        cam = self._input_camera()
        return (cam.fov_y, cam.width / cam.height) if cam is not None else (0.69, 1.0)

    def camera(self, name: str) -> Camera | None:
        """The novel camera `name` at the inputs' field of view and resolution."""
        g, ref = self.gizmos.get(name), self._input_camera()
        if g is None or ref is None:
            return None
        return camera_from_viser(g.wxyz, g.position, ref.fov_y, ref.width, ref.height, name)

    def request(self, name: str, priority: int = 0) -> None:
        if name in self.gizmos:
            self.worker.submit(("novel", name), lambda: self._render(name), priority=priority)

    def _render(self, name: str) -> None:
        cam = self.camera(name)
        if cam is None:
            return
        out = self.run.render(cam)
        if out is None:
            self.status.content = "_No model yet: training is starting._"
            return
        img = visualize_output(out, self.output.value)
        self.image.image = upscale(img, 192)
        self.frustums[name].image = img
        self.status.content = f"`{name}`: {self.output.value}, {cam.width}x{cam.height} px, step {self.run.step}"


class SnapToView:
    """Jump a client's camera to an input / mirrored / test view; show GT, render, error and beta^2.

    The client's own view then shows the view in its frame (`on_snap`: ground truth and render
    blended, the error or beta^2), with the frustums near it hidden.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        worker: RenderWorker,
        run: RunView,
        on_snap: Callable[[viser.ClientHandle, Camera, np.ndarray | None, str], None],
    ) -> None:
        self.worker, self.run, self.on_snap = worker, run, on_snap
        gui = server.gui
        self.select = gui.add_dropdown("View", ("(none)",))
        self.snap_btn = gui.add_button("Snap to view", icon=viser.Icon.FOCUS_2, hint="Moves your camera there")
        self.text = gui.add_markdown("_Pick a view and snap to it._")
        self.gt = gui.add_image(BLANK, label="Ground truth (flipped for mirrors)", format="jpeg", visible=False)
        self.pred = gui.add_image(BLANK, label="Render", format="jpeg", visible=False)
        self.err = gui.add_image(BLANK, label="|error|", format="jpeg", visible=False)
        self.beta2 = gui.add_image(BLANK, label="beta^2", format="jpeg", visible=False)
        self.shown: str | None = None  # the view whose images the panel shows
        self.views: dict[str, tuple[str, int, Camera, np.ndarray | None]] = {}
        self.alphas: dict[str, np.ndarray | None] = {}  # the true silhouettes of the test views
        self.snap_btn.on_click(lambda ev: self.snap(self.select.value, ev.client))

    def rebuild(self) -> None:
        """List the run's views (called on every new run)."""
        setup = self.run.setup
        self.views, self.alphas = {}, {}
        counts: dict[str, int] = {}
        for info in setup.cameras if setup is not None else []:
            if info.kind not in ("input", "mirror_init", "test"):
                continue
            k = counts.get(info.kind, 0)
            counts[info.kind] = k + 1
            label = {"input": "input", "mirror_init": "mirror", "test": "test"}[info.kind]
            self.views[f"{label} {k}: {info.camera.name}"] = (info.kind, k, info.camera, info.image)
            self.alphas[f"{label} {k}: {info.camera.name}"] = info.alpha
        self.select.options = tuple(self.views) or ("(none)",)

    def current_camera(self, key: str) -> Camera | None:
        v = self.views.get(key)
        if v is None:
            return None
        kind, k, cam, _ = v
        c2w = self.run.mirror_c2w
        if kind == "mirror_init" and c2w is not None and k < len(c2w):
            cam = cam.with_pose(c2w[k])  # the BA-refined pose
        return cam

    def snap(self, key: str, client: viser.ClientHandle | None) -> None:
        cam = self.current_camera(key)
        if cam is None:
            return
        if client is not None:
            setup = self.run.setup
            move_client_camera(client, cam, setup.sphere_center if setup is not None else None)
            self.on_snap(client, cam, self.views[key][3], key)
        self.worker.submit("snap", lambda: self._render(key), priority=0)

    def _render(self, key: str) -> None:
        cam = self.current_camera(key)
        v = self.views.get(key)
        if cam is None or v is None:
            return
        out = self.run.render(cam)
        if out is None:
            return
        gt = v[3]
        self.shown = key
        self.pred.image = upscale(to_uint8(out["rgb"]), 320)
        b2 = out.get("beta2")
        self.beta2.image = upscale(palette.colormap(b2, *palette.BETA2_RANGE), 320) if b2 is not None else BLANK
        if gt is not None:
            self.gt.image = upscale(to_uint8(gt), 320)
            self.err.image = upscale(error_map(out["rgb"], gt), 320)
            text = f"**{key}** at step {self.run.step}: PSNR **{image_psnr(out['rgb'], gt):.2f} dB**"
            st = structure_scores(out["rgb"], gt, out["opacity"], self.alphas.get(key))
            if st:  # the object's own scores: silhouette IoU, PSNR inside the object
                text += f", silhouette IoU **{st['iou']:.3f}**, object PSNR **{st['psnr_object']:.2f} dB**"
            self.text.content = text
        else:
            self.text.content = f"**{key}** at step {self.run.step} (no ground truth)"
        for img, shown in (
            (self.pred, True),
            (self.beta2, b2 is not None),
            (self.gt, gt is not None),
            (self.err, gt is not None),
        ):
            img.visible = shown

    def clear(self) -> None:
        """A camera left the snapped view: its images go, so the panel never shows a view you are not at."""
        if self.shown is None:
            return
        for img in (self.gt, self.pred, self.err, self.beta2):
            img.visible = False
        self.text.content = f"_You left **{self.shown}**. Pick a view and snap to it._"
        self.shown = None


def move_client_camera(client: viser.ClientHandle, cam: Camera, target: np.ndarray | None = None) -> None:
    """Put a browser camera exactly at a flipviz camera: position, viewing direction, up, fov."""
    c = cam.center
    forward = -cam.c2w[:3, 2]  # OpenGL: the camera looks along -z
    dist = float(np.linalg.norm(c - target)) if target is not None else 1.0
    with client.atomic():
        client.camera.fov = cam.fov_y
        client.camera.position = c
        client.camera.look_at = c + max(dist, 1e-3) * forward
        client.camera.up_direction = cam.c2w[:3, 1]
