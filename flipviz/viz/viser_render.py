"""Renders for the browser, at low priority so that training keeps its speed.

Every render the app asks of the trainer (novel cameras, snapped views, mirror scores, each
client's own view) goes through one `RenderWorker` thread. `trainer.render` shares the trainer's
lock with the training step, so the worker is duty-cycled: after a render that took t seconds
it idles t (1 - duty) / duty seconds, so renders hold the lock at most a `duty` fraction of the
wall time. Jobs are keyed (a newer job replaces a pending one with the same key), user requests
(priority 0) go before viewport refreshes (priority 1).

`ViewportRenderer` renders each client's browser camera as its background: a low resolution
while the camera moves, the full resolution once it has been still for `settle_s`, and a
refresh every `refresh_s` while training runs.
"""

from __future__ import annotations

import contextlib
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable, Hashable

import viser

from flipviz.viz.viser_common import OUTPUTS, camera_from_viser, visualize_output


@dataclass
class _Job:
    priority: int
    not_before: float
    seq: int
    fn: Callable[[], None]


class RenderWorker:
    """One background thread that runs render jobs, holding the trainer's lock <= `duty` of the time."""

    def __init__(self, duty: float = 0.25) -> None:
        self.duty = min(max(float(duty), 0.01), 1.0)
        self._jobs: dict[Hashable, _Job] = {}
        self._cv = threading.Condition()
        self._seq = 0
        self._stop = False
        self.busy_s = 0.0  # total seconds spent in jobs
        self.jobs_done = 0
        self._thread = threading.Thread(target=self._loop, name="flipviz-render", daemon=True)
        self._thread.start()

    def submit(self, key: Hashable, fn: Callable[[], None], priority: int = 1, delay: float = 0.0) -> None:
        """Queue `fn` under `key`; a pending job with that key is replaced (keeping the earlier start)."""
        with self._cv:
            self._seq += 1
            t = time.monotonic() + max(0.0, delay)
            old = self._jobs.get(key)
            if old is not None:
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
                ready = [(j.priority, j.not_before, j.seq, k) for k, j in self._jobs.items() if j.not_before <= now]
                if ready:
                    key = min(ready)[3]
                    return self._jobs.pop(key).fn
                wait = min((j.not_before for j in self._jobs.values()), default=now + 1.0) - now
                self._cv.wait(timeout=max(0.005, min(wait, 1.0)))
        return None

    def _loop(self) -> None:
        while True:
            fn = self._next()
            if fn is None:
                return
            t0 = time.perf_counter()
            try:
                fn()
            except Exception:  # a failed render must never kill the worker
                traceback.print_exc()
            dt = time.perf_counter() - t0
            self.busy_s += dt
            self.jobs_done += 1
            idle = dt * (1.0 - self.duty) / self.duty
            with self._cv:
                self._cv.wait_for(lambda: self._stop, timeout=idle)

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._jobs.clear()
            self._cv.notify_all()
        self._thread.join(timeout=10.0)


@dataclass
class ClientView:
    """Per-client state of the background ('your view') rendering."""

    client: viser.ClientHandle
    enabled: bool = True
    output: str = "RGB"
    last_move: float = 0.0
    renders: int = 0
    gui: list = field(default_factory=list)


class ViewportRenderer:
    """Renders each client's browser camera as its background image (adaptive resolution)."""

    def __init__(
        self,
        worker: RenderWorker,
        render: Callable[..., dict | None],
        is_training: Callable[[], bool],
        low_width: int = 64,
        full_width: int = 192,
        settle_s: float = 0.35,
        refresh_s: float = 5.0,
    ) -> None:
        self.worker = worker
        self.render = render  # (camera, outputs) -> dict or None when no model is ready
        self.is_training = is_training
        self.low_width, self.full_width = int(low_width), int(full_width)
        self.settle_s, self.refresh_s = float(settle_s), float(refresh_s)
        self.clients: dict[int, ClientView] = {}
        self._lock = threading.Lock()
        self._gui_lock = threading.Lock()

    def add_client(self, client: viser.ClientHandle, folder=None) -> ClientView:
        view = ClientView(client)
        with self._lock:
            self.clients[client.client_id] = view
        ctx = folder if folder is not None else contextlib.nullcontext()
        with self._gui_lock, ctx:  # a container is entered by one thread at a time
            cb = client.gui.add_checkbox("Render my view", True, hint="Background: the model seen from your camera")
            dd = client.gui.add_dropdown("My view shows", OUTPUTS, initial_value="RGB")
        view.gui = [cb, dd]

        @cb.on_update
        def _(_) -> None:
            view.enabled = cb.value
            if view.enabled:
                self.request(client.client_id)
            else:
                client.scene.set_background_image(None)

        @dd.on_update
        def _(_) -> None:
            view.output = dd.value
            self.request(client.client_id)

        @client.camera.on_update
        async def _(_) -> None:  # async: runs on viser's event loop, no thread hop per camera message
            view.last_move = time.monotonic()
            self.request(client.client_id)

        # The first camera message arrived before this (it is what makes a client 'connected'),
        # possibly before the callback above existed: render the initial view now.
        self.request(client.client_id)
        return view

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self.clients.pop(client_id, None)
        self.worker.cancel(lambda k: k == ("view", client_id))

    def request(self, client_id: int, delay: float = 0.0) -> None:
        self.worker.submit(("view", client_id), lambda: self._render(client_id), priority=1, delay=delay)

    def request_all(self) -> None:
        for cid in list(self.clients):
            self.request(cid)

    def _render(self, client_id: int) -> None:
        view = self.clients.get(client_id)
        if view is None or not view.enabled:
            return
        cam = view.client.camera
        try:
            wxyz, pos, fov = cam.wxyz.copy(), cam.position.copy(), float(cam.fov)
            aspect = max(cam.image_width, 1) / max(cam.image_height, 1)
        except AssertionError:  # no camera message yet
            return
        moving = time.monotonic() - view.last_move < self.settle_s
        width = self.low_width if moving else self.full_width
        height = max(8, round(width / aspect))
        cam = camera_from_viser(wxyz, pos, fov, width, height)
        out = self.render(cam, outputs=("rgb", "depth", "opacity", "beta2"))
        if out is None or client_id not in self.clients:
            return
        view.client.scene.set_background_image(visualize_output(out, view.output), format="jpeg", jpeg_quality=85)
        view.renders += 1
        if moving:  # come back for the full resolution once the camera has settled
            self.request(client_id, delay=self.settle_s)
        elif self.is_training():  # keep the still view up to date with training
            self.request(client_id, delay=self.refresh_s)
