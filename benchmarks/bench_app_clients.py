"""Training speed of the app with 0, 1 and 4 browser clients dragging their cameras.

Starts the real app (real trainer) in-process and connects real websocket clients on loopback
(flipviz.viz.viser_wsclient, viser's protocol). Each client orbits its camera at 30 Hz for 2 s,
holds still for 1 s (so the app renders its view at full resolution), and repeats until the
phase ends; every client reads everything the server sends (background images included).
Training speed = trainer steps / wall seconds in each phase. Target: with 4 clients, training
keeps >= 50% of its solo speed.

    python benchmarks/bench_app_clients.py --res 100 --seconds 30
"""

from __future__ import annotations

import asyncio
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from flipviz.viz.viser_app import App, AppConfig
from flipviz.viz.viser_wsclient import ViserTestClient


@dataclass
class BenchConfig:
    scene: str = "chair"
    res: int = 100
    batch_rays: int = 4096
    seconds: float = 30.0
    """Length of each phase."""
    clients: tuple[int, ...] = (0, 1, 4, 0)
    """Client counts, one phase each (the last 0 re-measures solo speed, for drift)."""
    view_width: int = 192
    render_duty: float = 0.25
    warmup_s: float = 20.0
    """Training time before the first phase (the first steps are slower)."""
    out: Path | None = None
    """Write the results as JSON here."""


async def drag(url: str, k: int, seconds: float, center: np.ndarray, radius: float) -> int:
    """One client: orbit (2 s at 30 Hz), hold still (1 s), repeat; returns how many background images arrived."""
    async with ViserTestClient(url) as c:
        t0 = time.monotonic()
        phase = 2 * math.pi * k / 4
        while time.monotonic() - t0 < seconds:
            for i in range(60):
                a = phase + 0.02 * i
                p = center + radius * np.array([math.cos(a), math.sin(a), 0.5])
                await c.send_camera(p, look_at=tuple(center), size=(600, 800))
                await asyncio.sleep(1 / 30)
            phase += 1.2
            await asyncio.sleep(1.0)
        return sum(m["type"] == "BackgroundImageMessage" and bool(m.get("rgb_data")) for m in c.messages)


def measure(app: App, n: int, seconds: float) -> dict:
    setup = app.setup
    center, radius = np.asarray(setup.sphere_center), float(setup.sphere_radius)
    url = f"ws://127.0.0.1:{app.port}"
    busy0, jobs0 = app.worker.busy_s, app.worker.jobs_done
    s0, t0 = app.trainer.step, time.perf_counter()

    async def phase() -> list[int]:
        if n == 0:
            await asyncio.sleep(seconds)
            return []
        return list(await asyncio.gather(*(drag(url, k, seconds, center, radius) for k in range(n))))

    images = asyncio.run(phase())
    dt = time.perf_counter() - t0
    steps = app.trainer.step - s0
    return {
        "clients": n,
        "seconds": round(dt, 2),
        "steps": steps,
        "steps_per_s": round(steps / dt, 2),
        "renders": app.worker.jobs_done - jobs0,
        "render_busy_frac": round((app.worker.busy_s - busy0) / dt, 3),
        "background_images_received": images,
    }


def main(bc: BenchConfig) -> list[dict]:
    cfg = AppConfig(
        scene=bc.scene, res=bc.res, batch_rays=bc.batch_rays, steps=10_000_000, no_rrd=True, port=0,
        images_every=0, checkpoint_every=0, eval_on_stop=False, out=Path(tempfile.mkdtemp()) / "run",
        view_width=bc.view_width, render_duty=bc.render_duty,
    )  # fmt: skip
    app = App(cfg).start()
    try:
        t = time.monotonic()
        while app.setup is None or app.trainer is None or app.step < 1:
            if app.status == "error" or time.monotonic() - t > 120:
                raise RuntimeError(f"training did not start: {app.status} {app.message}")
            time.sleep(0.2)
        time.sleep(bc.warmup_s)
        rows = []
        for n in bc.clients:
            r = measure(app, n, bc.seconds)
            rows.append(r)
            print(json.dumps(r), flush=True)
    finally:
        app.stop()
    solo = [r["steps_per_s"] for r in rows if r["clients"] == 0]
    solo_mean = float(np.mean(solo)) if solo else float("nan")
    print(f"\nscene {bc.scene}, res {bc.res}, batch {bc.batch_rays}, {bc.seconds:.0f} s per phase, duty {bc.render_duty}")
    print("clients | steps/s | vs solo | renders | render lock share")
    for r in rows:
        print(
            f"{r['clients']:7d} | {r['steps_per_s']:7.2f} | {r['steps_per_s'] / solo_mean:6.0%} | {r['renders']:7d} |"
            f" {r['render_busy_frac']:.0%}"
        )
    four = [r["steps_per_s"] for r in rows if r["clients"] == 4]
    if four:
        ok = min(four) >= 0.5 * solo_mean
        print(f"target (4 clients >= 50% of solo): {'met' if ok else 'NOT met'}")
    if bc.out is not None:
        Path(bc.out).write_text(json.dumps({"config": {k: str(v) for k, v in vars(bc).items()}, "rows": rows}, indent=2))
    return rows


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
