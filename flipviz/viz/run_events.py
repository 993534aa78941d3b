"""The trainer's events as the app's UI thread takes them.

The trainer calls `RunEvents` in its own thread: each event is copied under one lock, held only for
the copy, and training goes on. A few times a second the UI thread `take`s what is new (a new run's
setup, the latest step, the last test renders, a moved plane) and draws it. The curves the Train
and Mirror tabs plot grow here too, and are read under the same lock (`curves`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from flipviz.data.dataset import Plane
from flipviz.training.events import EndEvent, ImagesEvent, Observer, SetupEvent, StepEvent
from flipviz.viz.run_curves import RunCurves


@dataclass
class News:
    """What the UI thread takes: what arrived since it last took, and the latest step (which stays)."""

    setup: SetupEvent | None  # a new run, to build
    step: StepEvent | None  # the latest step of the current run
    images: ImagesEvent | None  # the last test renders and scalars
    plane: Plane | None  # the refined mirror plane of the last step that moved it


class RunEvents(Observer):
    """The current run's events, handed from the trainer's thread to the UI thread (see the module doc)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.step = 0  # optimisation steps done
        self.mirror_c2w: np.ndarray | None = None  # (M, 4, 4) the mirrored cameras' latest poses
        self.test_psnr: float | None = None  # the unobserved views' PSNR at the last evaluation
        self._taken: SetupEvent | None = None  # the run the UI thread built
        self._setup: SetupEvent | None = None
        self._step: StepEvent | None = None
        self._images: ImagesEvent | None = None
        self._plane: Plane | None = None
        self._curves: RunCurves | None = None

    # ---- the trainer's thread: copy and return
    def on_setup(self, event: SetupEvent) -> None:
        with self._lock:
            if event is self._taken or event is self._setup:
                return
            self._setup, self._curves = event, RunCurves.for_run(event)  # a new run: the last one's state goes
            self._step = self._images = self._plane = self.mirror_c2w = self.test_psnr = None

    def on_step(self, event: StepEvent) -> None:
        with self._lock:
            self._step, self.step = event, event.step
            if event.mirror_c2w is not None:
                self.mirror_c2w = event.mirror_c2w
            if event.plane is not None:
                self._plane = event.plane
            if self._curves is not None:
                self._curves.add_step(event)

    def on_images(self, event: ImagesEvent) -> None:
        with self._lock:
            self._images = event
            if "test_psnr" in event.scalars:
                self.test_psnr = float(event.scalars["test_psnr"])
                if self._curves is not None:
                    self._curves.add_test(event.step, self.test_psnr)

    def on_end(self, event: EndEvent) -> None:
        self.step = event.step

    # ---- the UI thread
    def take(self) -> News:
        """What is new since the last take (a new run's setup with its first steps)."""
        with self._lock:
            setup, self._setup = self._setup, None
            self._taken = setup or self._taken
            images, self._images = self._images, None
            plane, self._plane = self._plane, None
            return News(setup, self._step, images, plane)

    @contextmanager
    def curves(self) -> Iterator[RunCurves | None]:
        """The current run's curves, read under the lock the trainer's thread adds to them with (ms)."""
        with self._lock:
            yield self._curves

    def clear(self) -> None:
        """Forget the stopped run (the app restarts): nothing of it is taken or plotted any more."""
        with self._lock:
            self._taken = self._setup = self._step = self._images = self._plane = self._curves = None
            self.mirror_c2w, self.test_psnr, self.step = None, None, 0
