"""`--mirror-plane auto`: the object's mirror plane estimated from the input views alone.

1. a field fitted to the inputs alone: the run's own, after its first --estimate-after steps
   (trainer.py: the mirrors join then), or, with --estimate-after 0, a short separate B/L fit of the
   fast grid field (`estimate_plane`; the app's *Estimate plane* too);
2. the surface the inputs saw (the field's depth maps, back-projected) and, on a VOLUME_RES^3 lattice
   over the scene box, which voxels hold it and which the inputs saw: in front of (or within two
   voxels behind) the field's depth along an input ray, every voxel along a ray that hits nothing;
3. `geometry.symmetry.search_plane`: the reflection that maps the seen surface onto itself.

Nothing here looks at the test views or at the scene's true plane. The settings below (and the
scoring constants of geometry/symmetry.py) were tuned on the untouched built-in scenes (chair,
truck, mug, lamp; configurations 1 and 4) and measured on the turned ones, the other
configurations and lego by studies/bench_plane.py. The fit (500 steps of 512 rays, 24 samples)
took 8-12 s on the 2-core machine; 200 steps of 1024 rays left chair and lamp indistinguishable.
From the run's own field, steps 150 of 600 of the chair's configuration 1 (5 seeds): the search
took 1.5-2.8 s, and the planes were 0.27-1.14° off (the separate fit's: 0.29-1.36°, 10-12 s).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from flipviz.data.cameras import View
from flipviz.data.dataset import SceneData
from flipviz.errors import UserError
from flipviz.files import write_json
from flipviz.geometry.symmetry import PlaneEstimate, SymmetryVolume, search_plane
from flipviz.model import GridConfig, ModelConfig, RadianceModel
from flipviz.model.fit import fit

log = logging.getLogger("flipviz.training")

FIT_STEPS = 500
FIT_BATCH = 512
FIT_SAMPLES = 24
FIT_GRID = (32, 64)
VOLUME_RES = 64
DEPTH_RES = 64  # width of the depth maps that decide what the inputs saw


def symmetry_volume(model: RadianceModel, inputs: list[View], box: np.ndarray, res: int = VOLUME_RES) -> SymmetryVolume:
    """What the inputs saw, from a fitted model: their depth maps as surface points, and per voxel
    of a res^3 lattice over `box` whether it holds such points and whether some input ray reaches
    it before (or within two voxels after) its first surface."""
    box = np.asarray(box, np.float64)
    lattice = SymmetryVolume(np.zeros((0, 3)), np.zeros((res,) * 3), np.zeros((res,) * 3, bool), box).lattice()
    cell = (box[1] - box[0]) / (res - 1)
    seen = np.zeros(len(lattice), bool)
    surface: list[np.ndarray] = []
    for v in inputs:
        cam = v.camera.resized(DEPTH_RES)
        out = model.render_image(cam)
        hit = out["opacity"].reshape(-1) > 0.5
        o, d = cam.rays()
        surface.append(o[hit] + out["depth"].reshape(-1)[hit, None] * d[hit])
        depth = np.where(out["opacity"] > 0.5, out["depth"], np.inf)  # a ray that hits nothing sees all of it
        r, u, vis = cam.project(lattice)
        dist = np.linalg.norm(lattice[vis] - cam.center, axis=1)
        seen[np.flatnonzero(vis)[dist <= depth[r[vis], u[vis]] + 2.0 * cell.max()]] = True
    pts = np.concatenate(surface)
    pts = pts[np.all((pts >= box[0]) & (pts <= box[1]), axis=1)]
    idx = np.clip(np.round((pts - box[0]) / cell).astype(int), 0, res - 1)
    occ = np.zeros((res,) * 3, np.float32)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
    return SymmetryVolume(pts, occ, seen.reshape((res,) * 3), box)


def estimate_plane(inputs: list[View], scene: SceneData, device: str = "cpu", seed: int = 0) -> PlaneEstimate:
    """The mirror plane of the object the `inputs` see, with its confidence (module docstring), from a
    separate short fit. The run's random state is left as it was: a Flip run that drops its mirrors
    then trains exactly B/L."""
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[] if str(device) == "cpu" else None):
        torch.manual_seed(seed)
        field = GridConfig(grid_res=FIT_GRID, upsample_at=(0.3,))
        model = RadianceModel(
            ModelConfig(field=field, n_samples=FIT_SAMPLES),
            scene.bbox,
            scene.near,
            scene.far,
            with_beta=False,
            device=device,
        )
        fit(model, inputs, FIT_STEPS, batch_rays=FIT_BATCH, seed=seed)
        t_fit = time.perf_counter() - t0
        est = estimate_from_field(model, inputs, scene, seed)
    est.seconds = time.perf_counter() - t0
    est.meta.update({"fit_seconds": t_fit, "fit_steps": FIT_STEPS})
    return est


def estimate_from_field(
    model: RadianceModel, inputs: list[View], scene: SceneData, seed: int = 0, step: int = 0
) -> PlaneEstimate:
    """The mirror plane of a field fitted to the `inputs` alone (steps 2-3 of the module docstring);
    `step`: how many steps the field trained, for the record."""
    t0 = time.perf_counter()
    est = search_plane(symmetry_volume(model, inputs, scene.bbox), scene.up, scene.up_known, seed)
    est.seconds = time.perf_counter() - t0
    est.meta.update({"field_steps": step, "up_known": bool(scene.up_known)})
    log.info("%s (%.1f s)", est.summary(), est.seconds)
    return est


def read_estimate(path: Path | None) -> PlaneEstimate | None:
    """The estimate written to `path` (plane.json, --plane-file), or None when there is none."""
    if path is None or not path.is_file():
        return None
    try:
        return PlaneEstimate.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as e:
        raise UserError(
            f"cannot read the estimated plane {path} ({type(e).__name__}); delete it to estimate again"
        ) from None


def estimate_or_read(
    inputs: list[View], scene: SceneData, device: str, seed: int, saved: Path | None, shared: Path | None = None
) -> PlaneEstimate:
    """The estimate of this run: read back from `saved` (plane.json of the run being resumed, so that
    the mirrored poses the checkpoint refined stay the same) or from `shared` (--plane-file), else
    estimated now (and written to `shared`)."""
    for path in (saved, shared):
        if (est := read_estimate(path)) is not None:
            return est
    return shared_estimate(estimate_plane(inputs, scene, device, seed), shared)


def shared_estimate(est: PlaneEstimate, shared: Path | None) -> PlaneEstimate:
    """A new estimate, said when it is doubted, and written to `shared` (--plane-file) for other runs."""
    if not est.confident:
        log.warning("%s", est.summary())
    if shared is not None:
        write_json(shared, est.to_dict())
    return est
