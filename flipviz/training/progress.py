"""A tqdm progress bar that observes training: step, loss, batch PSNR, test PSNR, ETA."""

from __future__ import annotations

import sys

from tqdm import tqdm

from flipviz.training.events import EndEvent, ImagesEvent, Observer, SetupEvent, StepEvent


class ProgressObserver(Observer):
    def __init__(self, file=None, disable: bool = False) -> None:
        self.file = file if file is not None else sys.stderr
        self.disable = disable
        self.bar: tqdm | None = None
        self.postfix: dict[str, str] = {}

    def on_setup(self, event: SetupEvent) -> None:
        self.bar = tqdm(
            total=event.total_steps, desc=f"{event.method} {event.scene} cfg{event.config}",
            unit="step", file=self.file, disable=self.disable, dynamic_ncols=True,
        )  # fmt: skip

    def on_step(self, event: StepEvent) -> None:
        if self.bar is None:
            return
        self.bar.update(max(0, event.step - self.bar.n))  # tqdm's own rate gives the ETA
        s = event.scalars
        self.postfix.update(loss=f"{s.get('loss', float('nan')):.4f}", psnr=f"{s.get('psnr', float('nan')):.2f}")
        self.bar.set_postfix(self.postfix, refresh=False)

    def on_images(self, event: ImagesEvent) -> None:
        if self.bar is not None and "test_psnr" in event.scalars:
            self.postfix["test_psnr"] = f"{event.scalars['test_psnr']:.2f}"
            self.bar.set_postfix(self.postfix)

    def on_end(self, event: EndEvent) -> None:
        if self.bar is None:
            return
        self.bar.update(max(0, event.step - self.bar.n))
        self.bar.close()
        self.bar = None
        if event.status != "finished" and event.message:
            print(f"[flipviz] {event.status}: {event.message}", file=self.file)
