"""The README's screenshots of the app, from a real headless Chromium (see tests/browser.py).

    python studies/app_screenshots.py --out assets

1. app.png: the chair training (Flip+U), your view rendered at the canvas size;
2. app_snapped.png: snapped to an unobserved test view, ground truth and render blended half-half;
   app_scoring.png: Restart in the authors' setting and scoring asks first (the protocol, its cost);
   app_restart.png: Restart -> mug asks first (which run it replaces, where its checkpoint stays);
3. app_mirror.png: the mug with --unconfident-plane drop (its doubted plane's mirrors are not trained:
   "Show the mirrors anyway" draws them), its mirrored frustums coloured by their scores and showing
   where the flipped images disagree with the model;
5. app_compare.png: the Compare tab, the chair's Flip+U (A) side by side with a finished B/L run (B)
   from an unobserved test view, both scored;
4. app_capture.png: a robot's drive-by capture of the turned chair (`export-scene --trajectory
   driveby`) trained with `--mirror-plane auto`: the Mirror tab's estimated plane, its confidence
   and the score-against-azimuth chart;
6. app_plane.png: the chair trained from a mirror plane turned 10 degrees (the plane demo): the
   Mirror tab while training pulls the plane back, its trail and its error;
7. app_fog.png: the chair's B/L in flipviz's setting (A) side by side with B/L in the official code's
   setting (B, trained from the Compare tab), at an unobserved view: the fog of issue 22;
8. app_probe.png: snapped to an unobserved view, a pixel of the chair clicked: the pixel probe's reading
   and its marker; app_curves.png: the Mirror tab's charts over the steps (each mirrored camera's
   rotation error, the refined plane's error).
9. app_agreement.png: the mug at the defaults (its doubted plane tried): the Mirror tab's agreement
   chart after the gate dropped a mirror and the field went back to the join.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "studies")]
from browser import chromium, screenshot_png, wait_until  # noqa: E402
from test_browser import button, canvas_element, checkbox, choose, modal_open, tab  # noqa: E402

from flipviz.viz.app.app import App, AppConfig, check_run_input  # noqa: E402


@dataclass
class Args:
    out: Path = ROOT / "assets"
    steps_before: int = 700
    """Training steps before the first screenshot."""
    shots: str = "orbit,capture,compare,plane,fog,probe,agreement"
    """orbit: app.png, app_snapped.png, app_scoring.png, app_restart.png, app_mirror.png; capture:
    app_capture.png; compare: app_compare.png; plane: app_plane.png; fog: app_fog.png; probe: app_probe.png,
    app_curves.png; agreement: app_agreement.png."""


def main(args: Args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    if "orbit" in args.shots:
        orbit_shots(args)
    if "capture" in args.shots:
        capture_shot(args)
    if "compare" in args.shots:
        compare_shot(args)
    if "plane" in args.shots:
        plane_shot(args)
    if "fog" in args.shots:
        fog_shot(args)
    if "probe" in args.shots:
        probe_shots(args)
    if "agreement" in args.shots:
        agreement_shot(args)
    print(f"screenshots in {args.out}")


def open_page(d, port: int, settle_s: float) -> None:
    """Load the app, let it settle, close the "software WebGL" notice of headless Chromium."""
    d.get(f"http://127.0.0.1:{port}")
    wait_until(lambda: d.find_elements("xpath", "//canvas"), 60, what="the page")
    time.sleep(settle_s)
    for toast in d.find_elements("xpath", "//button[contains(@class, 'CloseButton')]"):
        toast.click()


def snap_to(d, app: App, prefix: str) -> None:
    """Views tab: snap the browser's camera to the first view whose name starts with `prefix`."""
    tab(d, "Views")
    choose(d, "View", next(k for k in app.snap.views if k.startswith(prefix)))
    button(d, "Snap to view")
    wait_until(  # the browser reported the snapped pose (a busy machine takes seconds)
        lambda: any(v.snapped is not None and v.snapped.arrived for v in app.views.clients.values()),
        60,
        what="the browser at the snapped view",
    )


def side_by_side_shot(d, app: App, path: Path) -> None:
    """Compare's side by side, once the server has it (B just loaded set the mode itself), then a
    screenshot after the finest pass of A and B."""
    time.sleep(2.0)
    choose(d, "Show", "side by side")
    wait_until(lambda: app.compare.mode_dd.value == "side by side", 30, what="side by side on the server")
    time.sleep(20.0)
    path.write_bytes(screenshot_png(d))


def capture_shot(args: Args) -> None:
    from flipviz.data.driveby import export_driveby

    data = export_driveby("chair-turned", Path(tempfile.mkdtemp()) / "drive", res=100)
    cfg = AppConfig.from_settings(
        data=data, mirror_plane="auto", no_rrd=True, port=0, out=Path(tempfile.mkdtemp()) / "run", images_every=100
    )
    cfg, scene = check_run_input(cfg)  # as `python app.py --data`: the 100 px capture trains at 100 px
    app = App(cfg, scene=scene).start()
    try:
        wait_until(lambda: app.step >= args.steps_before // 2, 600, what="training")
        with chromium() as d:
            open_page(d, app.port, settle_s=5.0)
            tab(d, "Mirror")
            checkbox(d, "Show plane preview", False)
            folder = d.find_elements("xpath", "//*[normalize-space(text())='Estimated plane']")
            d.execute_script("arguments[0].scrollIntoView({block: 'start'});", folder[0])
            time.sleep(3.0)
            (args.out / "app_capture.png").write_bytes(screenshot_png(d))
    finally:
        app.stop()


def compare_shot(args: Args) -> None:
    from flipviz.training.config import TrainConfig
    from flipviz.training.run import train

    b_dir = Path(tempfile.mkdtemp()) / "chair-bl"
    train(TrainConfig.from_settings(scene="chair", method="bl", out=b_dir, no_rrd=True))
    cfg = AppConfig.from_settings(
        scene="chair",
        no_rrd=True,
        port=0,
        out=Path(tempfile.mkdtemp()) / "run",
        images_every=100,
        steps=600,
        browse_root=(b_dir.parent,),
    )
    app = App(cfg).start()
    try:
        wait_until(lambda: app.status == "finished", 900, what="training A")
        with chromium() as d:
            open_page(d, app.port, settle_s=5.0)
            tab(d, "Mirror")
            checkbox(d, "Show plane preview", False)
            snap_to(d, app, "test 3")
            time.sleep(1.0)
            tab(d, "Compare")
            d.find_element("xpath", "//label[normalize-space()='Or a folder']/following::input[1]").send_keys(
                str(b_dir)
            )
            time.sleep(0.5)
            button(d, "Load run B")
            wait_until(lambda: app.compare.b is not None and app.compare.scores, 120, what="run B and its scores")
            side_by_side_shot(d, app, args.out / "app_compare.png")
    finally:
        app.stop()


def plane_shot(args: Args) -> None:
    from plane_demo import turned_plane_arg

    from flipviz.data.scenes import SCENES

    plane = turned_plane_arg(SCENES["chair"].symmetry_plane, 10.0, 0.0)
    cfg = AppConfig.from_settings(
        scene="chair",
        mirror_plane=plane,
        no_rrd=True,
        port=0,
        out=Path(tempfile.mkdtemp()) / "run",
        images_every=100,
        steps=600,
    )
    app = App(cfg).start()
    try:
        wait_until(lambda: app.step >= 350, 600, what="training")
        with chromium() as d:
            open_page(d, app.port, settle_s=5.0)
            tab(d, "Mirror")
            checkbox(d, "Show plane preview", False)
            wait_until(lambda: "Refined plane" in app.mirror.trail.text.content, 60, what="the refined plane")
            time.sleep(4.0)
            (args.out / "app_plane.png").write_bytes(screenshot_png(d))
    finally:
        app.stop()


def agreement_shot(args: Args) -> None:
    cfg = AppConfig.from_settings(
        scene="mug", no_rrd=True, port=0, images_every=100, out=Path(tempfile.mkdtemp()) / "run"
    )
    app = App(cfg).start()
    try:
        wait_until(lambda: any(app.scene.dropped), 900, what="the gate's first drop")
        at = app.step
        wait_until(lambda: app.step > at + 50, 300, what="training on after the drop")
        with chromium() as d:
            open_page(d, app.port, settle_s=5.0)
            tab(d, "Mirror")
            verdict = lambda: "Mirrored views dropped" in app.mirror.curves.verdict.content  # noqa: E731
            wait_until(verdict, 60, what="the gate's verdict")
            chart = d.find_element("xpath", "//*[starts-with(normalize-space(), 'Mirrors vs inputs')]")
            d.execute_script("arguments[0].scrollIntoView({block: 'center'});", chart)  # the ratio, the limit, the drop
            time.sleep(4.0)
            (args.out / "app_agreement.png").write_bytes(screenshot_png(d))
    finally:
        app.stop()


def fog_shot(args: Args) -> None:
    cfg = AppConfig.from_settings(
        scene="chair",
        method="bl",
        mirror_plane="official",
        no_rrd=True,
        port=0,
        images_every=100,
        steps=600,
        out=Path(tempfile.mkdtemp()) / "run",
    )
    app = App(cfg).start()
    try:
        wait_until(lambda: app.status == "finished", 900, what="training A")
        with chromium() as d:
            open_page(d, app.port, settle_s=5.0)
            snap_to(d, app, "test 3")
            tab(d, "Compare")
            choose(d, "B method", "bl")
            choose(d, "B setting", "authors")
            wait_until(lambda: app.compare.setting_dd.value == "authors", 30, what="the setting on the server")
            button(d, "Train B next to this run")
            wait_until(
                lambda: app.compare.b is not None and not app.compare.b.thread.is_alive(), 900, what="training B"
            )
            side_by_side_shot(d, app, args.out / "app_fog.png")
    finally:
        app.stop()


@contextmanager
def chair_in_browser(args: Args, **settings) -> Iterator[tuple[App, object]]:
    """The chair training at the defaults (but `settings`), past `args.steps_before` steps, in headless Chromium."""
    cfg = AppConfig.from_settings(
        scene="chair", no_rrd=True, port=0, out=Path(tempfile.mkdtemp()) / "run", images_every=100, **settings
    )
    app = App(cfg).start()
    try:
        wait_until(lambda: app.step >= args.steps_before, 600, what="training")
        with chromium() as d:
            open_page(d, app.port, settle_s=6.0)
            yield app, d
    finally:
        app.stop()


def probe_shots(args: Args) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    with chair_in_browser(args) as (app, d):
        snap_to(d, app, "test 3")
        time.sleep(4.0)
        ActionChains(d).move_to_element_with_offset(canvas_element(d), -20, 40).click().perform()  # the seat
        wait_until(lambda: app.probe.reading is not None, 60, what=f"the probe's reading ({app.probe.text.content})")
        time.sleep(3.0)
        (args.out / "app_probe.png").write_bytes(screenshot_png(d))
        tab(d, "Mirror")
        folder = d.find_element("xpath", "//*[normalize-space()='Over training']")
        d.execute_script("arguments[0].scrollIntoView({block: 'start'});", folder)
        time.sleep(3.0)
        (args.out / "app_curves.png").write_bytes(screenshot_png(d))


def asked(d, says: str, path: Path) -> None:
    """Restart training and screenshot the question once it says `says`."""
    button(d, "Restart training")
    wait_until(lambda: says in d.page_source, 30, what=f"the question saying {says!r}")
    time.sleep(1.0)  # (the modal's fade-in)
    path.write_bytes(screenshot_png(d))


def orbit_shots(args: Args) -> None:
    with chair_in_browser(args, unconfident_plane="drop") as (app, d):  # the chair's plane is confident: no change
        (args.out / "app.png").write_bytes(screenshot_png(d))
        snap_to(d, app, "test 3")
        tab(d, "Train")
        for v in app.views.clients.values():
            v.gui["blend"].value = 0.5
        time.sleep(4.0)
        (args.out / "app_snapped.png").write_bytes(screenshot_png(d))
        choose(d, "Setting", "authors")
        choose(d, "Scoring", "authors, every 4th view")
        asked(d, "Scored in the authors", args.out / "app_scoring.png")
        button(d, "Keep this run")
        wait_until(lambda: not modal_open(d), 30, what="the question closed")
        choose(d, "Setting", "fast")
        choose(d, "Scene", "mug")
        asked(d, "Replace this run", args.out / "app_restart.png")
        button(d, "Replace the run")
        wait_until(
            lambda: app.setup is not None and app.setup.scene == "mug" and app.step >= args.steps_before,
            600,
            what="the mug",
        )
        open_page(d, app.port, settle_s=4.0)  # a new scene: load the page afresh
        tab(d, "Mirror")
        if app.mirror.mirrors.dropped:  # the default gate doubts the mug's plane: its mirrors, drawn anyway
            button(d, "Show the mirrors anyway (not trained on)")
            wait_until(
                lambda: any("not trained on" in k for k in app.mirror.consistency.scores), 120, what="the scores"
            )
        else:
            choose(d, "Mirrored frustums show", "disagreement")
            checkbox(d, "Show plane preview", False)
            button(d, "Score mirrors")
            wait_until(lambda: any("now" in k for k in app.mirror.consistency.scores), 120, what="the scores")
        time.sleep(3.0)
        (args.out / "app_mirror.png").write_bytes(screenshot_png(d))


if __name__ == "__main__":
    main(tyro.cli(Args))
