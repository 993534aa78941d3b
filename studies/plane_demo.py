"""The plane-refinement demo (a script): start Flip+U from a mirror plane turned by --turn-deg and
watch training pull it back (training/flip.py: MirrorPlane).

    python studies/plane_demo.py --turn-deg 10 --out docs/results/plane_refine

Writes plane_demo.gif (left: the scene from above with the true plane in purple, the training plane
in orange and its trail; right: an unobserved test view as the model renders it) and
plane_demo.json (the plane's error at every logged step). The same run, live, in the browser:

    python app.py --scene chair --mirror-plane "0,0,0;0.985,0.174,0"
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import tyro

from flipviz.data.dataset import Plane
from flipviz.data.images import to_uint8
from flipviz.files import atomic_path, write_json
from flipviz.geometry.symmetry import plane_error
from flipviz.training.config import TrainConfig
from flipviz.training.events import Observer, StepEvent
from flipviz.training.trainer import Trainer
from flipviz.viz import palette


@dataclass
class DemoConfig:
    scene: str = "chair"
    """A built-in scene with a known symmetry plane (chair, truck, and their -turned versions)."""
    config: int = 1
    turn_deg: float = 10.0
    """The training plane starts at the true plane turned by this much about the vertical."""
    offset: float = 0.0
    """... and moved by this much along its normal (scene units)."""
    steps: int = 600
    frame_every: int = 20
    """Steps between GIF frames."""
    out: Path = Path("docs/results/plane_refine")


def turned_plane_arg(true: Plane, deg: float, offset: float) -> str:
    """--mirror-plane 'px,py,pz;nx,ny,nz' for `true` turned by `deg` about z and moved by `offset`."""
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    p, n = true.point + offset * true.normal, R @ true.normal
    return ",".join(f"{x:.6f}" for x in p) + ";" + ",".join(f"{x:.6f}" for x in n)


class Frames(Observer):
    """Every `every` steps: the plane's error, and a frame (top view | an unobserved view)."""

    def __init__(self, trainer: Trainer, every: int) -> None:
        self.tr, self.every = trainer, every
        self.log: list[dict] = []
        self.frames: list[np.ndarray] = []
        self.trail: list[np.ndarray] = []
        self.view = trainer.split.tests[len(trainer.split.tests) // 2]

    def on_step(self, e: StepEvent) -> None:
        if e.plane is None or (e.step % self.every and e.step != e.total_steps and e.step != 1):
            return
        self.log.append({"step": e.step, "error_deg": e.plane_err_deg, "error_offset": e.plane_err_offset})
        self.frames.append(self.frame(e))

    def frame(self, e: StepEvent) -> np.ndarray:
        true, plane = self.tr.scene.symmetry_plane, e.plane
        fig, (ax, im) = plt.subplots(1, 2, figsize=(6.4, 3.2), dpi=100)
        for p, colour, label in (
            (true, palette.TRUE_PLANE, "true plane"),
            (plane, palette.MIRROR_PLANE, "training plane"),
        ):
            t = np.cross([0.0, 0.0, 1.0], p.normal)[:2]
            t /= np.linalg.norm(t)
            ends = np.stack([p.point[:2] - 2.2 * t, p.point[:2] + 2.2 * t])
            ax.plot(ends[:, 0], ends[:, 1], color=np.array(colour) / 255, lw=2.5, label=label)
        self.trail.append(plane.point[:2] + 1.2 * plane.normal[:2])
        tr = np.array(self.trail)
        ax.plot(tr[:, 0], tr[:, 1], ".-", color=np.array(palette.MIRROR_PLANE) / 255, ms=3, lw=1)
        for v in self.tr.split.inputs:
            ax.plot(*v.camera.center[:2], "o", color=np.array(palette.CAMERA["input"]) / 255, ms=4)
        for c in self.tr.flip.mirror_cameras():
            ax.plot(*c.center[:2], "o", color=np.array(palette.CAMERA["mirror"]) / 255, ms=4)
        ax.plot(*self.view.camera.center[:2], "s", color="0.3", ms=5)
        ax.set_xlim(-4.5, 4.5), ax.set_ylim(-4.5, 4.5), ax.set_aspect("equal"), ax.set_xticks([]), ax.set_yticks([])
        ax.set_title(f"step {e.step}: {e.plane_err_deg:.2f}° / {e.plane_err_offset:.3f} off", fontsize=9)
        ax.legend(loc="lower left", fontsize=7)
        im.imshow(to_uint8(self.tr.render(self.view.camera, ("rgb",))["rgb"]))
        im.set_title(f"unobserved view {self.view.name}", fontsize=9)
        im.axis("off")
        fig.tight_layout()
        fig.canvas.draw()
        img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        plt.close(fig)
        return img


def main(cfg: DemoConfig) -> None:
    from flipviz.data import load_scene

    scene = load_scene(cfg.scene, None, 100)
    if scene.symmetry_plane is None:
        raise SystemExit(f"{cfg.scene} has no known symmetry plane")
    plane = turned_plane_arg(scene.symmetry_plane, cfg.turn_deg, cfg.offset)
    with tempfile.TemporaryDirectory() as tmp:
        tcfg = TrainConfig.from_settings(
            scene=cfg.scene,
            config=cfg.config,
            steps=cfg.steps,
            mirror_plane=plane,
            out=Path(tmp) / "run",
            no_rrd=True,
            images_every=0,
            checkpoint_every=0,
        )
        tr = Trainer(tcfg, scene)
        frames = Frames(tr, cfg.frame_every)
        tr.add_observer(frames)
        m = tr.run()
    cfg.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(cfg.out / "plane_demo.gif") as tmp_gif:
        iio.imwrite(tmp_gif, np.stack(frames.frames), extension=".gif", duration=150, loop=0)
    start = plane_error(tr.mirrors.plane, scene.symmetry_plane)
    write_json(
        cfg.out / "plane_demo.json",
        {
            "scene": cfg.scene,
            "config": cfg.config,
            "mirror_plane": plane,
            "start_error": start,
            "psnr": m.get("psnr"),
            "steps": frames.log,
        },
    )
    last = frames.log[-1]
    print(
        f"{cfg.scene}: plane {start[0]:.2f}° / {start[1]:.3f} -> {last['error_deg']:.2f}° / {last['error_offset']:.3f} "
        f"off the true plane; unobserved PSNR {m.get('psnr', float('nan')):.2f} dB; {cfg.out / 'plane_demo.gif'}"
    )


if __name__ == "__main__":
    main(tyro.cli(DemoConfig))
