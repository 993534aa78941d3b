"""Viewer benchmark: how fast a user sees the model in the browser, on this machine.

    python studies/bench_viewer.py [--out viewer.json]

Starts the real app (chair, 100 px, Flip+U, its default 3000 steps) in-process and, after
1000 steps (the grid at its final resolution), measures:
1. time from camera stop to a view >= 800 px wide (a 1280 x 800 canvas), while training and
   paused (targets: <= 3 s and <= 1.5 s), with the websocket client of tests/viser_client.py;
2. bake time of the live 3D preview, cells to splats (target <= 300 ms) and its payload per
   browser (target <= 8 MB);
3. frames per second of headless Chromium (software WebGL) orbiting the splat preview, and the
   server's render jobs meanwhile (target: none), when Chromium is installed;
4. training steps/s with 1 and 4 clients orbiting, against the solo phases around them
   (target >= 80%), with studies/bench_app_clients.py.
Timings depend on the machine's load: run it on an idle machine.
"""

from __future__ import annotations

import asyncio
import io
import json
import math
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "studies")]
from viser_client import ViserTestClient  # noqa: E402

from flipviz.viz.app.app import App, AppConfig  # noqa: E402


@dataclass
class Args:
    repeats: int = 5
    """Camera stops timed per condition."""
    canvas: tuple[int, int] = (800, 1280)
    """Browser canvas (height, width)."""
    orbit_s: float = 8.0
    """Length of the Chromium orbit."""
    client_phase_s: float = 20.0
    """Length of each phase of the training-speed measurement (0: skip it)."""
    warmup_steps: int = 1000
    """Training steps before measuring (a trained field has more opaque voxels to bake and render)."""
    out: Path | None = None


def jpeg_width(data: bytes) -> int:
    from PIL import Image

    return Image.open(io.BytesIO(data)).size[0]


async def time_to_view(app: App, args: Args, min_width: int = 800) -> list[float]:
    """Seconds from the last camera message of a short orbit to a background >= min_width wide."""
    c0, r = np.asarray(app.setup.sphere_center), float(app.setup.sphere_radius)
    times = []
    async with ViserTestClient(f"ws://127.0.0.1:{app.port}") as c:
        for k in range(args.repeats):
            for i in range(15):  # a quick orbit, then stop
                a = 0.9 * k + 0.03 * i
                await c.send_camera(
                    c0 + 1.6 * r * np.array([math.cos(a), math.sin(a), 0.6]), tuple(c0), size=args.canvas
                )
                await asyncio.sleep(1 / 30)
            n, t0 = len(c.messages), time.monotonic()
            m = await c.wait_for(
                lambda m: (
                    m["type"] == "BackgroundImageMessage"
                    and bool(m.get("rgb_data"))
                    and jpeg_width(m["rgb_data"]) >= min_width
                ),
                timeout=30,
                start=n,
            )
            times.append(time.monotonic() - t0)
            assert m is not None
            await asyncio.sleep(1.0)
    return times


def bake(app: App, repeats: int) -> dict:
    """The preview's bake: the field's cells (Trainer.point_cloud) made into the splats the browser
    gets in RGB (LivePreview.shown), timed together; the payload one browser receives."""
    secs, splats = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        baked = app.trainer.point_cloud()
        splats, _ = app.preview.shown(baked)
        secs.append(time.perf_counter() - t)
    return {
        "bake_ms_median": round(1000 * statistics.median(secs), 1),
        "cells": len(baked["points"]),
        "splats": len(splats),
        "payload_mb": round(splats.nbytes / 2**20, 2),
    }


def browser_orbit(app: App, seconds: float) -> dict | None:
    from browser import chromium, chromium_available

    if not chromium_available():
        return None
    from selenium.webdriver.common.action_chains import ActionChains

    with chromium() as d:
        d.get(app.url.replace("localhost", "127.0.0.1"))
        time.sleep(8.0)
        for v in list(app.views.clients.values()):  # the browser's own 3D preview only
            v.gui["enabled"].value = False
        app.preview.request()
        time.sleep(3.0)
        canvas = d.find_element("tag name", "canvas")
        d.execute_script("window.__frames = 0; (function f(){ window.__frames++; requestAnimationFrame(f); })();")
        jobs0, busy0 = app.worker.jobs_done, app.worker.busy_s
        f0, t0 = d.execute_script("return window.__frames;"), time.monotonic()
        chain = ActionChains(d, duration=10).move_to_element(canvas).click_and_hold()
        while time.monotonic() - t0 < seconds:
            for _ in range(20):
                chain.move_by_offset(6, 1)
            chain.perform()
            chain = ActionChains(d, duration=10)
        ActionChains(d).release().perform()
        dt = time.monotonic() - t0
        frames = d.execute_script("return window.__frames;") - f0
        return {
            "fps": round(frames / dt, 1),
            "server_render_jobs": app.worker.jobs_done - jobs0,
            "server_render_s": round(app.worker.busy_s - busy0, 2),
        }


def main(args: Args) -> dict:
    cfg = AppConfig.from_settings(
        scene="chair", no_rrd=True, port=0, checkpoint_every=0, eval_on_stop=False, out=Path(tempfile.mkdtemp()) / "run"
    )
    app = App(cfg).start()
    res: dict = {}
    try:
        while app.trainer is None or app.step < args.warmup_steps:
            time.sleep(0.5)
        res["while_training_s"] = asyncio.run(time_to_view(app, args))
        app.pause()
        time.sleep(1.0)
        res["paused_s"] = asyncio.run(time_to_view(app, args))
        res.update(bake(app, args.repeats))
        orbit = browser_orbit(app, args.orbit_s)  # paused: no bakes, no view renders expected
        if orbit:
            res.update(orbit)
    finally:
        app.stop()
    for k in ("while_training_s", "paused_s"):
        v = res[k]
        res[k.replace("_s", "_median_s")], res[k.replace("_s", "_max_s")] = (
            round(statistics.median(v), 2),
            round(max(v), 2),
        )
    if args.client_phase_s > 0:
        import bench_app_clients

        rows = bench_app_clients.main(bench_app_clients.BenchConfig(seconds=args.client_phase_s, warmup_s=10))
        res["steps_per_s_kept"] = {r["clients"]: r["vs_adjacent_solo"] for r in rows if r["clients"]}
    print(json.dumps(res, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main(tyro.cli(Args))
