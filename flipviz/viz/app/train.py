"""The Train tab: what the run is doing (status, step, PSNR, ETA, a PSNR plot) and its controls
(pause / resume, restart with another scene, method, configuration or step count)."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import viser

from flipviz.data.scenes import SCENES
from flipviz.training.config import METHODS, PRESETS, EvalConfig, TrainConfig
from flipviz.training.events import SetupEvent, StepEvent, split_label
from flipviz.viz import palette
from flipviz.viz.app.guard import guard_choice, guard_number

DATA_FOLDER = "(a data folder)"
CONFIGS = tuple(str(i) for i in range(1, 9))
SETTINGS = tuple(PRESETS)  # --preset: fast (flipviz's), authors (the official code's), paper (for a GPU)
SETTING_HINT = (
    "fast: flipviz's grid, white background; authors: the official code's choices (the last sample is "
    "the background: fog where no input looked); paper: those and the paper's NeRF, for a GPU"
)
MAX_STEPS = 10_000_000  # TrainConfig.validate's bound
FLIPVIZ_SCORING = "flipviz"
SCORINGS: dict[str, EvalConfig] = {  # --eval-views, --eval-tune-steps, --eval-every
    FLIPVIZ_SCORING: EvalConfig(),
    "authors, every 4th view": EvalConfig("orbit", 100, 4),  # as the budget study scores (study_table3.py)
    "authors, every view": EvalConfig("orbit", 100, 1),  # as the released code scores
}
SCORING_HINT = (
    "How the run is scored when it ends. flipviz: the 8 unobserved views at their poses. authors: as the "
    "released code scores, the orbit views the run did not train on, each pose first tuned 100 steps on its own "
    "ground truth (it looks at the test image; about 9 s a view at 200 px on 2 cores, 92 views on a built-in "
    "scene). Offered with the authors' and paper settings."
)
TUNED_VIEW_S = 9.0  # one view tuned 100 steps and scored, 200 px, 2 cores (measured with a study beside it)


@dataclass
class RunChoice:
    """What the Restart form asks for."""

    scene: str | None  # a built-in scene, or None with a data folder
    data: str | None
    method: str
    config: int
    steps: int
    preset: str
    scoring: str  # a key of the panel's scorings: how the run is scored at its end


def scorings(started: EvalConfig) -> dict[str, EvalConfig]:
    """The Scoring choices: flipviz's and the authors' (SCORINGS), and the command line's when it asked for
    another (e.g. --eval-every 2)."""
    if started in SCORINGS.values():
        return dict(SCORINGS)
    return SCORINGS | {f"as started: {started.words()}": started}


def run_choice(cfg: TrainConfig, choices: dict[str, EvalConfig]) -> RunChoice:
    """The Restart form's fields for the run `cfg` (what the form shows while it trains)."""
    data = str(cfg.data.path) if cfg.data.path else None
    scoring = next((k for k, e in choices.items() if e == cfg.eval), FLIPVIZ_SCORING)
    return RunChoice(
        None if data else cfg.data.scene, data, cfg.method, cfg.data.config, cfg.engine.steps, cfg.preset, scoring
    )


def scoring_settings(choice: RunChoice, choices: dict[str, EvalConfig]) -> dict[str, object]:
    """The eval settings (flat, by flag name) the choice's Scoring stands for."""
    return asdict(choices[choice.scoring])


def fmt_time(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def step_text(step: int, total: int, asked: int) -> str:
    """The Train tab's step count; a run that grew past the steps asked for (a drop sent the field back to
    the join, or a fresh field trained the inputs) says by how much and why."""
    text = f"step **{step}** / {total}"
    if total > asked:
        text += f" ({asked} asked + {total - asked} again after the mirrors' drop)"
    return text


class Pace:
    """Steps per second of wall time over the last `window_s` of running: the renders for the browsers,
    the evaluations and the checkpoints included (StepEvent.elapsed_s counts the steps alone, so an ETA
    from it ran 1.5-1.7x short). A pause or a new run starts it again."""

    def __init__(self, window_s: float = 60.0) -> None:
        self.window_s = window_s
        self.seen: deque[tuple[float, int]] = deque()  # (monotonic time, step), oldest first

    def add(self, step: int, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if self.seen and step < self.seen[-1][1]:
            self.seen.clear()  # the run went back (a rollback to the join): its pace starts again
        if not self.seen or step > self.seen[-1][1]:
            self.seen.append((now, step))
        while len(self.seen) > 2 and now - self.seen[1][0] > self.window_s:
            self.seen.popleft()

    def clear(self) -> None:
        self.seen.clear()

    def rate(self) -> float | None:
        """Steps per wall second (None until two steps were seen)."""
        if len(self.seen) < 2 or self.seen[-1][0] <= self.seen[0][0]:
            return None
        (t0, s0), (t1, s1) = self.seen[0], self.seen[-1]
        return (s1 - s0) / (t1 - t0)


def psnr_scales(rng: tuple[float, float]) -> dict:
    """The PSNR chart's scales: both curves on one fixed range. The test curve is NaN between
    evaluations (uPlot joins its points with spanGaps), and uPlot's automatic range fails on a
    series whose first value is NaN (no y axis, no curve: seen in Chromium), so the server sets it."""
    return {"x": {"time": False}, "y": {"auto": False, "range": rng}, "test": {"auto": False, "range": rng}}


class TrainPanel:
    def __init__(
        self,
        server: viser.ViserServer,
        on_pause: Callable[[], None],
        on_resume: Callable[[], None],
        on_restart: Callable[[RunChoice, viser.ClientHandle | None], None],
        tab: viser.GuiTabHandle,
        scoring: dict[str, EvalConfig] = SCORINGS,
    ) -> None:
        """Built inside `tab` (the Train tab), where a new PSNR chart goes when its range changes; `scoring`:
        the Scoring choices (`scorings`)."""
        gui = server.gui
        self.scorings = scoring
        self.server, self._tab = server, tab
        self.progress_md = gui.add_markdown("_Starting..._")
        self.progress_bar = gui.add_progress_bar(0.0, animated=False, color="orange")
        self.plot = self._psnr_chart((0.0, 1.0))
        self._plotted: tuple | None = None  # (points, last step, evaluations) of the curves shown
        self._range: tuple[float, float] = (0.0, 1.0)
        self.pace = Pace()  # steps per wall second, for the ETA
        self.pause_btn = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE)
        self.resume_btn = gui.add_button("Resume", icon=viser.Icon.PLAYER_PLAY, disabled=True)
        with gui.add_folder("Restart", expand_by_default=True):
            choices = (*SCENES, DATA_FOLDER)
            self.scene_dd = guard_choice(
                gui.add_dropdown("Scene", choices, hint="A built-in object, or your own folder"), choices
            )
            self.data_txt = gui.add_text(
                "Data folder", "", hint="A scene folder under the browse roots (--data, --browse-root)"
            )
            self.method_dd = guard_choice(gui.add_dropdown("Method", METHODS), METHODS)
            self.config_dd = guard_choice(gui.add_dropdown("Configuration", CONFIGS), CONFIGS)
            self.steps_num = guard_number(gui.add_number("Steps", 600, min=1, max=MAX_STEPS, step=1), 1, MAX_STEPS)
            self.setting_dd = guard_choice(gui.add_dropdown("Setting", SETTINGS, hint=SETTING_HINT), SETTINGS)
            names = tuple(scoring)
            self.scoring_dd = guard_choice(gui.add_dropdown("Scoring", names, hint=SCORING_HINT), names)
            self.restart_btn = gui.add_button("Restart training", icon=viser.Icon.REFRESH)
            self.restart_md = gui.add_markdown("")
        self.pause_btn.on_click(lambda _: on_pause())
        self.resume_btn.on_click(lambda _: on_resume())
        self.restart_btn.on_click(lambda ev: on_restart(self.choice(), ev.client))
        self.scene_dd.on_update(lambda _: self._show_data_field())
        self.setting_dd.on_update(lambda _: self._offer_scoring())
        self._show_data_field()
        self._offer_scoring()

    def _show_data_field(self) -> None:
        self.data_txt.visible = self.scene_dd.value == DATA_FOLDER

    def _offer_scoring(self) -> None:
        """The authors' scoring (tuned on the test images) goes with their settings: flipviz's setting is
        scored in flipviz's protocol."""
        fast = self.setting_dd.value == "fast"
        if fast and self.scoring_dd.value != FLIPVIZ_SCORING:
            self.scoring_dd.value = FLIPVIZ_SCORING
        self.scoring_dd.disabled = fast

    def choice(self) -> RunChoice:
        data = self.data_txt.value.strip() if self.scene_dd.value == DATA_FOLDER else None
        scene = None if data is not None else self.scene_dd.value
        return RunChoice(
            scene,
            data,
            self.method_dd.value,
            int(self.config_dd.value),
            int(self.steps_num.value),
            self.setting_dd.value,
            self.scoring_dd.value,
        )

    def ask(self, client: viser.ClientHandle, question: str, on_yes: Callable[[], None]) -> None:
        """Ask the browser that clicked Restart first (a modal of its own): a misplaced click replaced a
        finished 3000-step run."""
        gui = client.gui
        with gui.add_modal("Restart training?") as modal:
            gui.add_markdown(question)
            yes = gui.add_button("Replace the run", icon=viser.Icon.REFRESH, color="orange")
            no = gui.add_button("Keep this run", color="gray")

        def answer(go: bool) -> None:
            modal.close()
            if go:
                on_yes()

        yes.on_click(lambda _: answer(True))
        no.on_click(lambda _: answer(False))

    def say(self, text: str) -> None:
        """One line under the Restart button (why a restart was refused); cleared by the next run."""
        self.restart_md.content = text

    def show_run(self, run: RunChoice) -> None:
        """Put the form on the run that trains now (`run_choice`)."""
        self.scene_dd.value = DATA_FOLDER if run.data else run.scene
        self.data_txt.value = run.data or ""
        self.method_dd.value, self.config_dd.value, self.steps_num.value = run.method, str(run.config), run.steps
        self.setting_dd.value = run.preset
        self.scoring_dd.value = run.scoring
        self.restart_md.content = ""
        self.pace.clear()
        self._show_data_field()

    def set_controls(self, status: str) -> None:
        """Pause only while running, Resume only while paused."""
        self.pause_btn.disabled = status != "running"
        self.resume_btn.disabled = status != "paused"

    def _psnr_chart(self, rng: tuple[float, float], order: float | None = None) -> viser.GuiUplotHandle:
        """The PSNR chart on the range `rng`. A new range is a new chart: the browser's chart, given other
        scales, could keep a stale x range (steps 10-430 shown on [-5, -3.5]: no line drawn)."""
        return self.server.gui.add_uplot(
            (np.array([0.0, 1.0]), np.array([0.0, 0.0]), np.array([np.nan, np.nan])),
            (
                {"label": "steps trained"},
                {"label": "train batch", "stroke": palette.hex_color(palette.CAMERA["mirror"]), "width": 2},
                {
                    "label": "unobserved views",
                    "stroke": palette.hex_color(palette.CAMERA["test"]),
                    "width": 2,
                    "spanGaps": True,
                    "points": {"show": True, "size": 6},
                    "scale": "test",
                },
            ),
            title="PSNR (dB)",
            scales=psnr_scales(rng),
            aspect=1.6,
            visible=False,
            order=order,
        )

    def set_plot(self, data: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """The run's PSNR curves (RunCurves.psnr_data: steps, training batch, unobserved views); hidden
        until it has two points (a new run's plot starts empty, never the last run's or a degenerate
        one); sent only when it changed."""
        x, _, test = data
        self.plot.visible = len(x) >= 2
        key = (len(x), x[-1] if len(x) else None, int(np.isfinite(test).sum()))
        if len(x) < 2 or key == self._plotted:
            return
        self._plotted = key
        finite = np.concatenate([c[np.isfinite(c)] for c in data[1:]])
        rng = (float(np.floor(finite.min())) - 1.0, float(np.ceil(finite.max())) + 1.0)  # whole dB: rarely changes
        if rng != self._range:
            self._range = rng
            with self._tab:
                old, self.plot = self.plot, self._psnr_chart(rng, order=self.plot.order)
            old.remove()
        self.plot.data = data
        self.plot.visible = True

    def show_progress(
        self,
        setup: SetupEvent | None,
        status: str,
        ev: StepEvent | None,
        test_psnr: float | None,
        render_share: float,
        message: str,
        run_dir: str | None,
    ) -> None:
        """The status text. During a restart it shows no number of the run that is going away."""
        head = f"**{setup.scene} | {setup.method} | {split_label(setup.config)}**" if setup else "**flipviz**"
        parts = [f"status: **{status}**"]
        if status == "running" and ev is not None:
            self.pace.add(ev.step)
        elif status != "finished":
            self.pace.clear()  # a pause is no part of the pace (a finished run's stays: Restart's estimate)
        if ev is not None and status not in ("restarting", "starting"):
            s = ev.scalars
            wall = self.pace.rate()
            parts += [
                step_text(ev.step, ev.total_steps, setup.cfg.engine.steps if setup else ev.total_steps),
                f"loss {s.get('loss', float('nan')):.4f}",
                f"PSNR {s.get('psnr', float('nan')):.2f} dB",
            ]
            if wall is not None and wall > 0 and status == "running":
                parts.append(f"{wall:.1f} steps/s, ETA {fmt_time((ev.total_steps - ev.step) / wall)} at this pace")
            self.progress_bar.value = 100.0 * ev.step / max(1, ev.total_steps)
            if test_psnr is not None:
                parts.append(f"unobserved views PSNR **{test_psnr:.2f} dB**")
        elif status in ("restarting", "starting"):
            self.progress_bar.value = 0.0
        if status == "running":  # the share of the machine renders take from training (nothing to share otherwise)
            parts.append(f"render thread busy {100 * render_share:.0f}% of the last 10 s (waits for a step included)")
        text = head + "\n\n" + " | ".join(parts)
        if message:
            text += f"\n\n_{message}_"
        if run_dir is not None:
            text += f"\n\nrun folder: `{run_dir}`"
        if self.progress_md.content != text:
            self.progress_md.content = text
