"""A tqdm progress bar that observes training: step, loss, batch PSNR, test PSNR, ETA."""

from __future__ import annotations

import sys
from typing import Any

from tqdm import tqdm

from flipviz.training.events import EndEvent, ImagesEvent, Observer, SetupEvent, StepEvent


class ProgressObserver(Observer):
    """One bar per run. The bench gives each worker its own row (`position`) and label."""

    def __init__(
        self,
        file=None,
        disable: bool = False,
        label: str | None = None,
        position: int | None = None,
        leave: bool = True,
        bar_cls: Any = tqdm,
    ) -> None:
        self.file = file if file is not None else sys.stderr
        self.disable, self.label, self.position, self.leave, self.bar_cls = disable, label, position, leave, bar_cls
        self.bar: Any = None
        self.postfix: dict[str, str] = {}

    def on_setup(self, event: SetupEvent) -> None:
        desc = f"{event.scene} {self.label or event.method} " + (f"cfg{event.config}" if event.config else "inputs")
        kw = (
            {}
            if self.bar_cls is not tqdm
            else dict(
                file=self.file, disable=self.disable, dynamic_ncols=True, position=self.position, leave=self.leave
            )
        )
        self.bar = self.bar_cls(total=event.total_steps, desc=desc, unit="step", **kw)

    def on_step(self, event: StepEvent) -> None:
        if self.bar is None:
            return
        if event.total_steps != self.bar.total:  # the field restarted after the mirrors were dropped
            self.bar.total = event.total_steps
        self.bar.update(max(0, event.step - self.bar.n))  # tqdm's own rate gives the ETA
        s = event.scalars
        self.postfix.update(loss=f"{s.get('loss', float('nan')):.4f}", psnr=f"{s.get('psnr', float('nan')):.2f}")
        self.bar.set_postfix(self.postfix, refresh=False)
        if event.step == event.total_steps:  # the final evaluation follows and takes a few seconds
            self.bar.set_description(f"{self.bar.desc}: evaluating the unobserved views", refresh=True)

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
        if event.status != "finished" and event.message and self.leave:
            print(f"[flipviz] {event.status}: {event.message}", file=self.file)
