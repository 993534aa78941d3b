"""Renders for the browser, at low priority so that training keeps its speed.

Every render the app asks of the trainer (novel cameras, snapped views, mirror scores, each
client's own view) goes through one `RenderWorker` thread. `trainer.render` shares the trainer's
lock with the training step, so the worker is duty-cycled: after a render that took t seconds
it idles t (1 - duty) / duty seconds, so renders hold the lock at most a `duty` fraction of the
wall time. Jobs are keyed (a newer job replaces a pending one with the same key), user requests
(priority 0) go before viewport renders (1) and background work (2: preview bakes, refreshes);
background work keeps its share of the duty cycle without delaying what a user waits for.

`ViewportRenderer` renders each client's browser camera as its background, at the canvas's
aspect ratio: nothing (the live 3D preview shows) or a coarse image while the camera moves, then,
once it has been still for `settle_s`, progressively finer passes up to the client's "max
resolution"; a camera move cancels the passes still to come. While training runs, the still view
is refreshed every `refresh_s`. The background carries its depth, so frustums behind the object
are hidden by it. A snapped view (`snap`) shows the view's ground truth, the render, their error
or beta^2 in the view's own frame, blended as the client chooses. It sees the run through `RunView`
(run_view.py), and the 3D preview and the Compare tab through the two small protocols below.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
import traceback
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import viser

from flipviz.data.cameras import Camera
from flipviz.data.images import to_uint8
from flipviz.viz import palette
from flipviz.viz.app.guard import bounded, guard_choice, guard_number
from flipviz.viz.app.poses import camera_from_viser
from flipviz.viz.images import (
    OUTPUTS,
    ScalarView,
    beta2_over_render,
    error_map,
    output_range,
    resize_nearest,
    view_depth,
    visualize_output,
)
from flipviz.viz.run_view import RunView, depth_range

BACKGROUND = 2  # priority of periodic work nobody waits for (preview bakes, refreshes of a still view)


@dataclass
class _Job:
    priority: int
    not_before: float
    seq: int
    fn: Callable[[], None]


class RenderWorker:
    """One background thread that runs render jobs, holding the trainer's lock <= `duty` of the time."""

    def __init__(self, duty: float = 0.25) -> None:
        if not 0.01 <= duty <= 1.0:  # NaN too: a wait of NaN seconds never returns
            raise ValueError(f"render duty must be in 0.01..1, got {duty!r}")
        self.duty = float(duty)
        self._jobs: dict[Hashable, _Job] = {}
        self._cv = threading.Condition()
        self._seq = 0
        self._stop = False
        self.busy_s = 0.0  # total seconds spent in jobs
        self._spans: collections.deque[tuple[float, float]] = collections.deque(maxlen=4096)  # recent jobs (start, end)
        self._running_since: float | None = None  # the job in progress
        self._last_priority = 0
        self._background_at = 0.0  # background jobs wait until then (their share of the duty cycle)
        self.jobs_done = 0
        self._thread = threading.Thread(target=self._loop, name="flipviz-render", daemon=True)
        self._thread.start()

    def submit(
        self, key: Hashable, fn: Callable[[], None], priority: int = 1, delay: float = 0.0, debounce: bool = False
    ) -> None:
        """Queue `fn` under `key`; a pending job with that key is replaced. It keeps the earlier start,
        unless `debounce`: then the job waits `delay` from now (e.g. until a moving camera is still)."""
        with self._cv:
            self._seq += 1
            t = time.monotonic() + max(0.0, delay)
            old = self._jobs.get(key)
            if old is not None and not debounce:
                t = min(t, old.not_before)
                priority = min(priority, old.priority)
            self._jobs[key] = _Job(priority, t, self._seq, fn)
            self._cv.notify()

    def cancel(self, match: Callable[[Hashable], bool]) -> None:
        with self._cv:
            for k in [k for k in self._jobs if match(k)]:
                del self._jobs[k]

    def pending(self, key: Hashable) -> bool:
        with self._cv:
            return key in self._jobs

    def _next(self) -> Callable[[], None] | None:
        with self._cv:
            while not self._stop:
                now = time.monotonic()
                ready = [
                    (j.priority, j.not_before, j.seq, k)
                    for k, j in self._jobs.items()
                    if j.not_before <= now and (j.priority < BACKGROUND or now >= self._background_at)
                ]
                if ready:
                    prio, _, _, key = min(ready)
                    self._last_priority = prio
                    return self._jobs.pop(key).fn
                wait = min((j.not_before for j in self._jobs.values()), default=now + 1.0) - now
                self._cv.wait(timeout=max(0.005, min(wait, 1.0)))
        return None

    def _loop(self) -> None:
        while True:
            fn = self._next()
            if fn is None:
                return
            t0 = self._running_since = time.monotonic()
            try:
                fn()
            except Exception:  # a failed render must never kill the worker
                traceback.print_exc()
            t1 = time.monotonic()
            with self._cv:
                self._spans.append((t0, t1))
                self._running_since = None
            dt = t1 - t0
            self.busy_s += dt
            self.jobs_done += 1
            idle = dt * (1.0 - self.duty) / self.duty
            if self._last_priority >= BACKGROUND:  # background work pays its idle time before the
                self._background_at = time.monotonic() + idle  # next background job, not before yours
                continue
            with self._cv:
                self._cv.wait_for(lambda: self._stop, timeout=idle)

    def share(self, window_s: float = 10.0) -> float:
        """The fraction of the last `window_s` seconds spent in jobs, the one running now included (0..1)."""
        now = time.monotonic()
        with self._cv:
            spans = [*self._spans, *([(self._running_since, now)] if self._running_since is not None else [])]
        return sum(max(0.0, b - max(a, now - window_s)) for a, b in spans) / window_s

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._jobs.clear()
            self._cv.notify_all()
        self._thread.join(timeout=10.0)


MIN_WIDTH, MAX_WIDTH = 128, 1920  # "Max resolution": the finest pass of a view (bounded on the server)
MIN_ASPECT, MAX_ASPECT = 0.25, 4.0  # a canvas outside these is rendered at the nearest bound
SNAP_ARRIVAL_S = 10.0  # a browser that never reports the snapped pose in this long has left it


@dataclass
class Snapped:
    """A client snapped to a view: its camera, and its reference image (ground truth, or flipped)."""

    camera: Camera
    reference: np.ndarray | None
    name: str
    since: float = field(default_factory=time.monotonic)
    arrived: bool = False  # the browser has reported this pose: a later, different pose means it moved away

    def left(self, at_view: bool) -> bool:
        """Whether the browser left the view. Until it reports the snapped pose, a report of another pose was
        sent before the snap reached it (or on the way) and does not count, for up to SNAP_ARRIVAL_S."""
        return not at_view and (self.arrived or time.monotonic() - self.since > SNAP_ARRIVAL_S)


@dataclass
class ClientView:
    """Per-client state of the background ('your view') rendering."""

    client: viser.ClientHandle
    enabled: bool = True
    output: str = "RGB"
    max_width: int = 800
    per_frame: bool = False
    snap_layer: str = "blend"
    blend: float = 1.0  # 0: the reference image, 1: the render
    snapped: Snapped | None = None
    version: int = 0  # bumped by every camera move: passes of an older version are dropped
    last_move: float = 0.0
    renders: int = 0
    gui: dict = field(default_factory=dict)
    sending: threading.Lock = field(default_factory=threading.Lock)  # a finished render vs. a switch-off


SNAP_LAYERS = ("blend", "|error|", "beta^2")


def pass_line(width: int, pass_idx: int, n_passes: int) -> str:
    """What the background of a view is: a coarse pass (the finer one is on its way) or the finest."""
    if pass_idx + 1 < n_passes:
        return f"_Your view: coarse pass {pass_idx + 1} of {n_passes}, {width} px wide; the full resolution follows._"
    return f"_Your view: full resolution, {width} px wide._"


class Preview(Protocol):
    """The browser-drawn 3D preview (viser_preview.LivePreview), shown while a camera moves."""

    on: bool

    def set_visible(self, client_id: int, visible: bool) -> None: ...


class CompareView(Protocol):
    """The Compare tab (viser_compare.ComparePanel): while on, its view of runs A and B replaces ours."""

    def compose(
        self, cam: Camera, out_a: dict, snapped: Snapped | None
    ) -> tuple[np.ndarray, tuple | None, np.ndarray | None] | None:
        """(background image, colour scale or None, depth or None), or None while Compare is off."""
        ...


class ViewportRenderer:
    """Renders each client's browser camera as its background image (progressive, canvas-sized)."""

    def __init__(
        self,
        worker: RenderWorker,
        run: RunView,
        preview: Preview,
        compare: CompareView,
        on_unsnap: Callable[[], None],
        max_width: int = 800,
        settle_s: float = 0.25,
        refresh_s: float = 5.0,
    ) -> None:
        self.worker, self.run = worker, run  # the model renders through `run`; its setup gives the depth scale
        self.preview = preview  # the browser-drawn 3D preview, shown while a camera moves (app/preview.py)
        self.compare = compare  # the Compare tab: its view of A and B replaces ours while on (app/compare.py)
        self.on_unsnap = on_unsnap  # a camera left its snapped view: the app brings back what it hid
        self.max_width = int(
            min(max(max_width, MIN_WIDTH), MAX_WIDTH)
        )  # the slider's own range (--view-width 64 broke it)
        self.settle_s, self.refresh_s = float(settle_s), float(refresh_s)
        self.clients: dict[int, ClientView] = {}
        self._lock = threading.Lock()
        self._gui_lock = threading.Lock()

    # ---- clients ----------------------------------------------------------------------------
    def add_client(self, client: viser.ClientHandle, folder=None) -> ClientView:
        view = ClientView(client, max_width=self.max_width)
        ctx = folder if folder is not None else contextlib.nullcontext()
        with self._gui_lock, ctx:  # a container is entered by one thread at a time
            g = client.gui
            view.gui = {
                "enabled": g.add_checkbox("Render my view", True, hint="Background: the model seen from your camera"),
                "pass": g.add_markdown("_Your view: not rendered yet._"),  # which pass the background is
                "output": guard_choice(g.add_dropdown("My view shows", OUTPUTS, initial_value="RGB"), OUTPUTS),
                "max_width": guard_number(
                    g.add_slider(
                        "Max resolution",
                        MIN_WIDTH,
                        MAX_WIDTH,
                        64,
                        view.max_width,
                        hint="Width in pixels of the finest pass of your view",
                    ),
                    MIN_WIDTH,
                    MAX_WIDTH,
                ),
                "per_frame": g.add_checkbox("beta^2 per frame", False, hint="Colour beta^2 on this frame's range"),
                "colorbar": g.add_image(np.full((46, 320, 3), 255, np.uint8), label="Colour scale", format="png"),
                "snap_layer": guard_choice(
                    g.add_dropdown("Snapped view shows", SNAP_LAYERS, initial_value="blend"), SNAP_LAYERS
                ),
                "blend": guard_number(g.add_slider("Ground truth <-> render", 0.0, 1.0, 0.05, 1.0), 0.0, 1.0),
            }
        view.gui["colorbar"].visible = False
        with self._lock:  # rendered from now on (its GUI exists)
            self.clients[client.client_id] = view

        def setter(attr: str, cast=lambda v: v):
            def on_update(_) -> None:
                with view.sending:  # a render finishing now sees the change (or is sent before it)
                    setattr(view, attr, cast(view.gui[attr].value))
                    if attr == "enabled" and not view.enabled:
                        view.version += 1  # a render under way is dropped, not sent over the preview
                        client.scene.set_background_image(None)
                        self.preview.set_visible(client.client_id, True)
                self.request(client.client_id)

            return on_update

        for attr, cast in (
            ("enabled", bool),
            ("output", str),
            ("max_width", int),
            ("per_frame", bool),
            ("snap_layer", str),
            ("blend", float),
        ):
            view.gui[attr].on_update(setter(attr, cast))

        @client.camera.on_update
        async def _(_) -> None:  # async: runs on viser's event loop, no thread hop per camera message
            self.moved(client.client_id)

        # The first camera message arrived before this (it is what makes a client 'connected'),
        # possibly before the callback above existed: render the initial view now.
        self.request(client.client_id)
        return view

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self.clients.pop(client_id, None)
        self.worker.cancel(lambda k: k == ("view", client_id))

    # ---- scheduling -------------------------------------------------------------------------
    def moved(self, client_id: int) -> None:
        """The camera moved: drop the passes under way, show the 3D preview, render once still."""
        view = self.clients.get(client_id)
        if view is None:
            return
        if view.snapped is not None and self.at(view, view.snapped.camera):
            view.snapped.arrived = True  # the browser reports the snapped pose (the server's own set is no report)
        now = time.monotonic()
        moving_already = now - view.last_move < self.settle_s
        view.last_move, view.version = now, view.version + 1
        if not self.preview.on:  # no 3D preview: a coarse render follows the camera
            self.request(client_id)
            return
        if not moving_already and view.enabled:
            view.client.scene.set_background_image(None)  # the browser's own 3D preview, at full frame rate
            self.preview.set_visible(client_id, True)
        self.request(client_id, delay=self.settle_s, debounce=True)

    def request(self, client_id: int, delay: float = 0.0, debounce: bool = False) -> None:
        view = self.clients.get(client_id)
        if view is None:
            return
        version = view.version
        self.worker.submit(
            ("view", client_id), lambda: self._render(client_id, version, 0), priority=1, delay=delay, debounce=debounce
        )

    def request_all(self) -> None:
        for cid in list(self.clients):
            self.request(cid)

    def unsnap_all(self) -> None:
        """A new run: no client stays snapped to a view of the old one."""
        for view in list(self.clients.values()):
            view.snapped = None
            view.version += 1

    def snap(self, client_id: int, snapped: Snapped) -> None:
        view = self.clients.get(client_id)
        if view is not None:
            view.snapped = snapped
            view.version += 1
            self.request(client_id)

    # ---- rendering --------------------------------------------------------------------------
    def passes(self, view: ClientView, canvas_w: int) -> list[int]:
        """Widths of the progressive passes: a quarter, then the target (canvas width up to max)."""
        target = max(64, min(int(canvas_w), int(bounded(view.max_width, MIN_WIDTH, MAX_WIDTH, MIN_WIDTH))))
        return [target // 4, target] if target >= 256 else [target]

    def _camera(self, view: ClientView, pass_idx: int) -> tuple[Camera, int] | None:
        cam = view.client.camera
        try:
            wxyz, pos, fov = cam.wxyz.copy(), cam.position.copy(), float(cam.fov)
            cw, ch = max(int(cam.image_width), 1), max(int(cam.image_height), 1)
        except AssertionError:  # no camera message yet
            return None
        if not 0.01 < fov < 3.1:  # a degenerate field of view from a client: nothing to render
            return None
        aspect = min(max(cw / ch, MIN_ASPECT), MAX_ASPECT)
        widths = self.passes(view, cw)
        width = widths[min(pass_idx, len(widths) - 1)]
        return camera_from_viser(wxyz, pos, fov, width, max(8, round(width / aspect))), len(widths)

    def at(self, view: ClientView, cam: Camera) -> bool:
        """The client's camera is at `cam`'s pose (it has not moved away from a snapped view)."""
        try:
            c2w = camera_from_viser(view.client.camera.wxyz, view.client.camera.position, 1.0, 8, 8).c2w
        except AssertionError:
            return False
        return bool(
            np.allclose(c2w[:3, 3], cam.c2w[:3, 3], atol=1e-3) and np.allclose(c2w[:3, :3], cam.c2w[:3, :3], atol=1e-3)
        )

    def _render(self, client_id: int, version: int, pass_idx: int, refresh: bool = False) -> None:
        view = self.clients.get(client_id)
        if view is None or not view.enabled or view.version != version:
            return  # gone, switched off, or the camera moved since: a newer request is queued
        if refresh and not self.run.training:
            return  # a refresh for a model that no longer changes (paused, finished): nothing new to send
        moving = time.monotonic() - view.last_move < self.settle_s
        if moving and self.preview.on:  # the browser draws the 3D preview meanwhile
            return self.request(client_id, delay=self.settle_s, debounce=True)
        if view.snapped is not None and view.snapped.left(self.at(view, view.snapped.camera)):
            view.snapped = None  # the camera was moved away (checked once still: a snap may animate)
            self.on_unsnap()
        got = self._camera(view, 0 if moving else pass_idx)
        if got is None:
            return
        cam, n_passes = got
        out = self.run.render(cam, outputs=("rgb", "depth", "opacity", "beta2"))
        if out is None or view.version != version or client_id not in self.clients:
            return
        composed = self.compare.compose(
            cam, out, view.snapped
        )  # the Compare tab's view (it says its own depth), or ours
        image, bar, depth = composed if composed is not None else (*self._compose(view, cam, out), view_depth(cam, out))
        with view.sending:
            if view.version != version or client_id not in self.clients:
                return  # moved or switched off while this rendered: a newer request is queued, or none is wanted
            try:
                view.client.scene.set_background_image(image, format="jpeg", jpeg_quality=88, depth=depth)
                line = pass_line(cam.width, 0 if moving else pass_idx, n_passes)
                if view.gui["pass"].content != line:
                    view.gui["pass"].content = line
                view.gui["colorbar"].visible = bar is not None
                if bar is not None:
                    view.gui["colorbar"].image = palette.colorbar(*bar)
            except RuntimeError as e:  # the client left while this rendered: viser removed its GUI handles
                if "removed" not in str(e):
                    raise
                return
            view.renders += 1
            if not moving and pass_idx + 1 == n_passes:
                self.preview.set_visible(client_id, False)  # the exact view replaces the preview
        if moving:  # a coarse frame while the camera moves; the passes once it is still
            return self.request(client_id, delay=self.settle_s, debounce=True)
        if pass_idx + 1 < n_passes:  # the next, finer pass
            self.worker.submit(("view", client_id), lambda: self._render(client_id, version, pass_idx + 1), priority=1)
        elif self.run.training:  # keep the still view up to date with training
            self.worker.submit(
                ("view", client_id),
                lambda: self._render(client_id, version, pass_idx, refresh=True),
                priority=BACKGROUND,
                delay=self.refresh_s,
            )

    def _compose(self, view: ClientView, cam: Camera, out: dict) -> tuple[np.ndarray, tuple | None]:
        """The background image and its colour scale (lo, hi, label), or None for RGB."""
        scalars = ScalarView(depth_range=depth_range(self.run.setup), per_frame=view.per_frame)
        snapped = view.snapped
        if snapped is None or snapped.reference is None:
            rng = output_range(out, view.output, scalars)
            return visualize_output(out, view.output, scalars), rng
        # A snapped view: the reference image sits in the centre of the canvas, at the view's field of view.
        rgb = to_uint8(out["rgb"])
        h = cam.height
        w = max(1, min(cam.width, round(h * snapped.reference.shape[1] / snapped.reference.shape[0])))
        x0 = (cam.width - w) // 2
        ref = resize_nearest(np.asarray(snapped.reference, np.float32), w, h)
        mine = out["rgb"][:, x0 : x0 + w]
        if view.snap_layer == "|error|":
            rgb[:, x0 : x0 + w] = error_map(mine, ref)
            return rgb, (*palette.ERROR_RANGE, "|render - reference|")
        if view.snap_layer == "beta^2" and out.get("beta2") is not None:
            rgb[:, x0 : x0 + w] = beta2_over_render(
                {k: v[:, x0 : x0 + w] for k, v in out.items() if v is not None}, *palette.BETA2_RANGE
            )
            return rgb, (*palette.BETA2_RANGE, "beta^2")
        a = float(view.blend)
        rgb[:, x0 : x0 + w] = to_uint8((1.0 - a) * ref + a * np.clip(mine, 0, 1))
        return rgb, None
