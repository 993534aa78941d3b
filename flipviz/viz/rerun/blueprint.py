"""The default Rerun layout of a run: the 3D scene on the left; image grids and curves on the right.

Entity layout written by `flipviz.viz.rerun.observer` (all names sanitised by `entity_name`):
    world                              z-up world coordinates
    world/sphere, world/mirror_plane   fitted sphere, mirror plane (+ /normal arrow), true plane
    world/cameras/<kind>/<name>        static cameras: input, test, mirror_init, mirror_true, upper
    world/cameras/mirror/<name>        refined mirrored cameras (pose per step)
    world/trajectories                 one segment per mirrored camera per logged step
    world/field                        the field as Gaussian splats, at a few steps (splats.py)
    views/test/<name>/{render,gt,error,depth,opacity}
    views/mirror/<name>/{render,flipped,beta2,depth,opacity}
    curves/{train,lr,test}/<key>, curves/mirror/<quantity>
"""

from __future__ import annotations

import re

import numpy as np
import rerun.blueprint as rrb

STEP = "step"  # the one timeline


def entity_name(name: str) -> str:
    """A camera or scalar name made safe as one entity-path part."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "_"


def _view2d(origin: str, name: str) -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin=origin, name=name)


def make_blueprint(
    test_names: list[str], mirror_names: list[str], center: np.ndarray | None = None, radius: float = 4.0
) -> rrb.Blueprint:
    """3D view on the left, seen from above the camera ring; test / mirrored image grids, beta^2 grid
    and curves (each quantity on its own axis) on the right."""
    t = [entity_name(n) for n in test_names]
    m = [entity_name(n) for n in mirror_names]
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    eye = rrb.EyeControls3D(position=c + radius * np.array([1.1, -1.3, 1.5]), look_target=c, eye_up=(0.0, 0.0, 1.0))
    scene = rrb.Spatial3DView(
        origin="/world",
        contents=["$origin/**", "- /world/field"],
        name="scene",
        eye_controls=eye,
        # Trajectories are logged one segment per step: show every segment up to the cursor.
        time_ranges=rrb.VisibleTimeRange(
            STEP, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
        ),
    )
    # The splats of the last bake at or before the cursor only (latest-at), with the cameras around them.
    model = rrb.Spatial3DView(
        origin="/world", contents=["/world/field", "/world/cameras/**"], name="model (splats)", eye_controls=eye
    )
    test_grid = rrb.Grid(
        contents=[
            _view2d(f"/views/test/{n}/{part}", title)
            for n in t
            for part, title in (("render", n), ("gt", "GT"), ("error", "err"))
        ],
        grid_columns=6,
        name="test: render | GT | error",
    )
    mirror_grid = rrb.Grid(
        contents=[
            _view2d(f"/views/mirror/{n}/{part}", title)
            for n in m
            for part, title in (("render", n.removesuffix("_flip")), ("flipped", "flip"), ("beta2", "b2"))
        ],
        grid_columns=6,
        name="mirrored: render | flipped | beta^2",
    )
    depth_grid = rrb.Grid(
        contents=[
            _view2d(f"/views/test/{n}/{part}", title) for n in t for part, title in (("depth", n), ("opacity", "op"))
        ],
        grid_columns=8,
        name="test: depth | opacity",
    )
    tabs = [test_grid, mirror_grid, depth_grid] if m else [test_grid, depth_grid]
    beta2_grid = rrb.Grid(
        contents=[_view2d(f"/views/mirror/{n}/beta2", n.removesuffix("_flip")) for n in m],
        grid_columns=max(1, len(m)),
        name="beta^2 of the mirrored views",
    )
    curves = rrb.Tabs(
        rrb.Horizontal(
            rrb.TimeSeriesView(origin="/curves/train/loss", name="loss"),
            rrb.TimeSeriesView(origin="/curves/train/psnr", name="PSNR, training batch (dB)"),
            rrb.TimeSeriesView(origin="/curves/test", name="PSNR, test views (dB)"),
            rrb.TimeSeriesView(origin="/curves/mirror/rot_change_deg", name="mirror rotation change (deg)"),
            rrb.TimeSeriesView(origin="/curves/mirror/rot_err_deg", name="mirror rotation error (deg)"),
            name="curves",
        ),
        rrb.Horizontal(
            rrb.TimeSeriesView(origin="/curves/lr/lr_field", name="field learning rate"),
            rrb.TimeSeriesView(origin="/curves/lr/lr_pose", name="pose learning rate"),
            rrb.TimeSeriesView(origin="/curves/mirror/trans_change", name="mirror translation change"),
            rrb.TimeSeriesView(origin="/curves/mirror/trans_err", name="mirror translation error"),
            name="more curves",
        ),
    )
    right = [rrb.Tabs(contents=tabs, active_tab=0)]
    shares = [3.0]
    if m:
        right.append(beta2_grid)
        shares.append(1.0)
    right.append(curves)
    shares.append(1.6)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(scene, model, active_tab=0),
            rrb.Vertical(contents=right, row_shares=shares),
            column_shares=[1.0, 1.2],
        ),
        rrb.TimePanel(timeline=STEP, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )
