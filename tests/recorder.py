"""The one observer the tests record a run's events with (training/events.py)."""

from __future__ import annotations

from flipviz.training.events import EndEvent, ImagesEvent, Observer, SetupEvent, StepEvent


class Recorder(Observer):
    """Keeps every event the trainer emitted, in order: to compare with what a recording, a table or a
    checkpoint holds."""

    def __init__(self) -> None:
        self.setup: SetupEvent | None = None
        self.steps: list[StepEvent] = []
        self.images: list[ImagesEvent] = []
        self.end: EndEvent | None = None

    def on_setup(self, e: SetupEvent) -> None:
        self.setup = e

    def on_step(self, e: StepEvent) -> None:
        self.steps.append(e)

    def on_images(self, e: ImagesEvent) -> None:
        self.images.append(e)

    def on_end(self, e: EndEvent) -> None:
        self.end = e
