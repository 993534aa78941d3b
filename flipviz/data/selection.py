"""Protocol-free runs: which frames of a scene are the inputs, and which are held out for evaluation.

`--inputs` takes
    ""                the capture's own split (`train_filenames`), else every frame
    "all"             every frame
    "0,3,5-9"         frame indices and ranges
    "az:-60..120"     frames whose camera sits at an azimuth in [-60, 120] degrees (wrapping) around
                      the object's centre: about the scene's up axis, 0 along the world x axis
                      projected off up, counter-clockwise seen from above
The held-out frames are the evaluation views: the capture's `test_filenames` when it has them,
else every frame that is not an input. The protocol's 200-view orbit split stays
`flipviz.data.protocol`, which the bench uses.
"""

from __future__ import annotations

import re

import numpy as np

from flipviz.data.cameras import azimuth_deg
from flipviz.data.dataset import DatasetError, SceneData
from flipviz.data.protocol import Split

AZIMUTH = re.compile(r"^az:\s*(-?\d+(?:\.\d*)?)\s*\.\.\s*(-?\d+(?:\.\d*)?)$")
USAGE = "use '', 'all', indices like '0,3,5-9', or an azimuth range like 'az:-60..120'"


def camera_azimuth(scene: SceneData, point: np.ndarray) -> float:
    """Azimuth (degrees, [0, 360)) of `point` around the scene's centre and up axis (module docstring)."""
    center = scene.center if scene.center is not None else scene.bbox.mean(0)
    return azimuth_deg(np.asarray(point, dtype=np.float64) - center, scene.up)


def _indices(spec: str, available: list[int]) -> list[int]:
    out: set[int] = set()
    for part in spec.split(","):
        lo, _, hi = part.strip().partition("-")
        if not lo.isdigit() or (hi and not hi.isdigit()):
            raise DatasetError(f"bad --inputs {spec!r}: {USAGE}")
        out.update(range(int(lo), int(hi or lo) + 1))
    missing = sorted(out - set(available))
    if missing:
        raise DatasetError(
            f"--inputs {spec!r}: no frame {missing[0]} (the scene has frames {available[0]}..{available[-1]})"
        )
    return sorted(out)


def input_frames(scene: SceneData, spec: str) -> list[int]:
    """The frame indices `spec` chooses as inputs (module docstring)."""
    frames = sorted(scene.views)
    spec = spec.strip()
    if spec == "":
        return list(scene.splits.get("train", frames))
    if spec == "all":
        return frames
    m = AZIMUTH.match(spec)
    if m:
        lo, hi = (float(x) % 360.0 for x in m.groups())
        inside = lambda a: lo <= a <= hi if lo <= hi else a >= lo or a <= hi  # noqa: E731 - a range may wrap
        return [i for i in frames if inside(camera_azimuth(scene, scene.views[i].camera.center))]
    return _indices(spec, frames)


def select_split(scene: SceneData, spec: str) -> Split:
    """Inputs chosen by `spec`; tests: the capture's test frames, else all the others; no Upper views."""
    inputs = input_frames(scene, spec)
    if len(inputs) < 4:
        raise DatasetError(
            f"--inputs {spec!r} chooses {len(inputs)} frame(s); a run needs at least 4 (the camera sphere)"
        )
    chosen = set(inputs)
    tests = [i for i in scene.splits.get("test", sorted(scene.views)) if i not in chosen]
    return Split(0, [scene.views[i] for i in inputs], [scene.views[i] for i in tests], [])
