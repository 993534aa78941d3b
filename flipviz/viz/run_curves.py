"""The curves the app plots over the steps of a run, gathered from the training events.

- PSNR of the training batch (every StepEvent) and of the unobserved test views (every ImagesEvent);
- each mirrored camera's rotation error against its exact reflection through the true plane, or,
  where no true plane is known, its change from the initial pose (what BA moved);
- the mirror plane's angle and offset error against the true plane, or its change from where
  training started it (only for runs that refine the plane);
- the mirrors' disagreement with the inputs (training/flip.py: Agreement), pooled and each mirror's
  own (up to its drop), against the limit above which they are dropped, and the step each one was.

The trainer's thread adds (`add_step`, `add_test`); the app's UI tick reads thinned copies as uPlot
data: one x column and one column per series, NaN where a series has no value (uPlot draws its points
and joins them with `spanGaps`). The x column counts the steps trained: after a drop the run goes back
to the join (--after-drop rollback) or to step 0 (restart) and trains the steps again, and uPlot draws
nothing of an x column that goes back; the curves go on from where the drop was instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flipviz.data.dataset import Plane
from flipviz.geometry.symmetry import plane_error
from flipviz.training.events import SetupEvent, StepEvent

MAX_POINTS = 400  # per curve sent to a browser


def thin(n: int, keep: np.ndarray | None = None, max_points: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most about `max_points` of n evenly spread rows, always with the last one and the
    rows in `keep` (e.g. the sparse test evaluations)."""
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).astype(int)) if n else np.zeros(0, int)
    return np.union1d(idx, keep) if keep is not None and len(keep) else idx


@dataclass
class RunCurves:
    """One run's curves (see the module doc)."""

    start_plane: Plane | None = None  # the plane training starts from (its change is plotted without truth)
    true_plane: Plane | None = None
    steps: list[float] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)  # training batch, dB (NaN when not reported)
    test: dict[float, float] = field(default_factory=dict)  # step -> PSNR of the unobserved views, dB
    mirror_steps: list[float] = field(default_factory=list)
    mirror_deg: list[np.ndarray] = field(default_factory=list)  # (M,) per mirror step
    mirror_vs_truth: bool = False  # mirror_deg is the error against the exact reflections
    plane_steps: list[float] = field(default_factory=list)
    plane_deg: list[float] = field(default_factory=list)
    plane_offset: list[float] = field(default_factory=list)
    limit: float = float("inf")  # --disagreement-limit (all the mirrors, on their pooled ratio)
    mirror_limit: float = float("inf")  # --mirror-disagreement-limit (one mirror, on its own)
    agree_steps: list[float] = field(default_factory=list)
    disagreement: list[float] = field(default_factory=list)
    mirror_ratio: list[np.ndarray] = field(default_factory=list)  # (M,) per agreement step, NaN once dropped
    dropped_at: int | None = None  # the step at which the agreement gate had dropped every mirror
    mirror_dropped_at: tuple[int | None, ...] = ()  # (M,) the step each mirror was dropped at (None: kept)
    drop_ratio: dict[int, float] = field(default_factory=dict)  # mirror -> its ratio when it was dropped
    after_drop: str = "rollback"  # what the run does after a drop (--after-drop)
    planned_steps: int = 0  # the run's steps at setup
    restarted: bool = False  # the run grew longer after a drop (--after-drop restart or rollback)
    again: int = 0  # the steps trained again after drops (the run's growth): x = step + again
    drop_x: dict[int, float] = field(default_factory=dict)  # mirror -> the x of its drop

    @classmethod
    def for_run(cls, setup: SetupEvent) -> RunCurves:
        f = setup.cfg.flip
        return cls(
            start_plane=setup.plane,
            true_plane=setup.true_plane,
            limit=f.disagreement_limit,
            mirror_limit=f.mirror_disagreement_limit,
            after_drop=f.after_drop,
            planned_steps=setup.total_steps,
        )

    @property
    def plane_vs_truth(self) -> bool:
        return self.true_plane is not None

    def add_step(self, ev: StepEvent) -> None:
        before, self.again = self.again, max(0, ev.total_steps - self.planned_steps) if self.planned_steps else 0
        s = float(ev.step + self.again)  # the steps trained so far (see the module doc)
        p = ev.scalars.get("psnr")
        self.steps.append(s)
        self.psnr.append(float(p) if p is not None and np.isfinite(p) else float("nan"))
        deg = ev.mirror_rot_err_deg if ev.mirror_rot_err_deg is not None else ev.mirror_rot_change_deg
        if deg is not None and (not self.mirror_deg or len(deg) == len(self.mirror_deg[0])):
            self.mirror_vs_truth = ev.mirror_rot_err_deg is not None
            self.mirror_steps.append(s)
            self.mirror_deg.append(np.asarray(deg, np.float64))
        if ev.mirror_dropped_at is not None:
            for i, at in enumerate(ev.mirror_dropped_at):
                if at is not None and i not in self.drop_x:
                    self.drop_x[i] = float(at + before)  # (its step, in the branch it was dropped in)
                if at is not None and i not in self.drop_ratio and self.mirror_ratio:
                    self.drop_ratio[i] = float(self.mirror_ratio[-1][i])  # its last measure before it left
            self.mirror_dropped_at = tuple(ev.mirror_dropped_at)
        d = ev.scalars.get("disagreement")
        if d is not None and np.isfinite(d):  # never a leading NaN: uPlot's range would break
            self.agree_steps.append(s)
            self.disagreement.append(float(d))
            if ev.mirror_ratio is not None and len(ev.mirror_ratio) == len(self.mirror_dropped_at):
                gone = np.array([i in self.drop_x and self.drop_x[i] < s for i in range(len(self.mirror_dropped_at))])
                self.mirror_ratio.append(np.where(gone, np.nan, np.asarray(ev.mirror_ratio, np.float64)))
        if ev.scalars.get("mirrors_trained") == 0.0 and self.dropped_at is None:
            self.dropped_at = int(ev.step)
        self.restarted = self.restarted or ev.total_steps > self.planned_steps > 0
        if ev.plane is not None:
            ref = self.true_plane if self.true_plane is not None else self.start_plane
            if ref is not None:
                # plane error = (angle between normals, distance of the point from the reference plane)
                deg_off = (
                    (ev.plane_err_deg, ev.plane_err_offset)
                    if ev.plane_err_deg is not None
                    else plane_error(ev.plane, ref)
                )
                self.plane_steps.append(s)
                self.plane_deg.append(float(deg_off[0]))
                self.plane_offset.append(float(deg_off[1]))

    def add_test(self, step: int, psnr: float) -> None:
        if np.isfinite(psnr):
            self.test[float(step + self.again)] = float(psnr)

    # ---- uPlot data (x first, then one column per series) -----------------------------------
    def psnr_data(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(steps, training-batch PSNR, test PSNR), the test column NaN between evaluations."""
        x = np.union1d(np.asarray(self.steps), np.fromiter(self.test, float, len(self.test)))
        train = np.full(len(x), np.nan)
        train[np.searchsorted(x, self.steps)] = self.psnr
        test = np.full(len(x), np.nan)
        if self.test:
            test[np.searchsorted(x, list(self.test))] = list(self.test.values())
        idx = thin(len(x), np.flatnonzero(np.isfinite(test)))
        return x[idx], train[idx], test[idx]

    def mirror_data(self) -> tuple[np.ndarray, ...]:
        """(steps, one rotation column per mirrored camera), in degrees."""
        if not self.mirror_steps:
            return ()
        idx = thin(len(self.mirror_steps))
        deg = np.stack(self.mirror_deg)[idx]
        return (np.asarray(self.mirror_steps)[idx], *deg.T)

    def agreement_data(self) -> tuple[np.ndarray, ...]:
        """(steps, disagreement, its limit, a mirror's own limit, then each mirror's own ratio where measured),
        ratios of squared errors."""
        if not self.agree_steps:
            return ()
        idx = thin(len(self.agree_steps))
        x = np.asarray(self.agree_steps)[idx]
        limits = [np.full(len(x), v if np.isfinite(v) else np.nan) for v in (self.limit, self.mirror_limit)]
        each = tuple(np.stack(self.mirror_ratio)[idx].T) if len(self.mirror_ratio) == len(self.agree_steps) else ()
        return x, np.asarray(self.disagreement)[idx], *limits, *each

    def plane_data(self) -> tuple[np.ndarray, ...]:
        """(steps, angle in degrees, offset in scene units)."""
        if not self.plane_steps:
            return ()
        idx = thin(len(self.plane_steps))
        return tuple(np.asarray(a)[idx] for a in (self.plane_steps, self.plane_deg, self.plane_offset))
