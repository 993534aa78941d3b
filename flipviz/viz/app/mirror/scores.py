"""The Mirror tab's evidence: the preview frustums of a plane you try, and the consistency scores.

    PlanePreview   the mirrored cameras a plane would give (pale orange, carrying the flipped images),
                   linked to their inputs; moved live as the plane moves, coloured once scored
    MirrorScores   the consistency of each mirrored view: PSNR of the model seen from that camera
                   against its flipped image (low where the symmetry assumption fails), as a table and
                   as the frustums' colours; what the mirrored frustums show (the flipped image, its
                   disagreement with the model, or beta^2)

The lesson (app/mirror/tab.py) decides what is scored (`Scoring`): the preview's cameras, while you move the
plane or look at a doubted plane's mirrors, else the mirrored cameras training uses now.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import viser

from flipviz.data.cameras import Camera
from flipviz.data.images import to_uint8
from flipviz.training.evaluate import image_psnr
from flipviz.training.events import ImagesEvent
from flipviz.viz import palette
from flipviz.viz.app.guard import guard_choice
from flipviz.viz.app.poses import to_viser_pose
from flipviz.viz.app.render import RenderWorker
from flipviz.viz.app.scene import RunScene
from flipviz.viz.images import error_map, resize_nearest, thumbnail
from flipviz.viz.run_view import RunView

FRUSTUM_IMAGES = ("flipped image", "disagreement", "beta^2")


class PlanePreview:
    """The initial mirrored cameras of a plane being tried, drawn under /preview."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.handles: list[viser.CameraFrustumHandle] = []
        self.frame: viser.FrameHandle | None = None
        self.cams: list[Camera] = []

    def show(
        self, cams: list[Camera], inputs: list[Camera], flipped: list, radius: float, visible: bool, moved: bool
    ) -> None:
        """Draw (first call of a run) or move the frustums to `cams`; link each to its input camera. `moved`:
        the plane moved, so no score belongs to these poses yet (the frustums lose their score colours)."""
        scene, r = self.server.scene, radius
        self.cams = cams
        with self.server.atomic():
            if not self.handles:
                self.frame = scene.add_frame("/preview", show_axes=False, visible=visible)
                for k, (cam, img) in enumerate(zip(cams, flipped)):
                    wxyz, pos = to_viser_pose(cam.c2w)
                    self.handles.append(
                        scene.add_camera_frustum(
                            f"/preview/{k}",
                            fov=cam.fov_y,
                            aspect=cam.width / cam.height,
                            scale=0.07 * r,
                            color=palette.CAMERA["mirror_init"],
                            image=thumbnail(img) if img is not None else None,
                            wxyz=wxyz,
                            position=pos,
                            thickness=0.01 * r / 4.0,
                            cast_shadow=False,
                            receive_shadow=False,
                        )
                    )
            else:
                for h, cam in zip(self.handles, cams):
                    h.wxyz, h.position = to_viser_pose(cam.c2w)
            links = np.stack([np.stack([a.center, b.center]) for a, b in zip(inputs, cams)]).astype(np.float32)
            scene.add_line_segments(
                "/preview/links", links, palette.CAMERA["mirror_init"], thickness=1.5, thickness_units="screen"
            )
            if moved:
                for h in self.handles:
                    h.color = palette.CAMERA["mirror_init"]

    def set_visible(self, visible: bool) -> None:
        if self.frame is not None:
            self.frame.visible = visible

    def wear(self, scores: list[float], images: list[np.ndarray | None]) -> None:
        """Each frustum takes its score's colour and, where given, an image (the flipped one otherwise kept)."""
        for h, s, img in zip(self.handles, scores, images):
            h.color = palette.score_color(s)
            if img is not None:
                h.image = thumbnail(img)

    def clear(self) -> None:
        self.handles, self.frame, self.cams = [], None, []


@dataclass
class Scoring:
    """What to score now: the cameras, their flipped images and names, the table column's label, and
    the preview whose frustums wear the scores (None: the run's mirrored frustums do)."""

    cams: list[Camera]
    flipped: list[np.ndarray | None]
    names: list[str]
    label: str
    preview: PlanePreview | None


class MirrorScores:
    """What the mirrored frustums show, *Score mirrors*, *Show the mirrors anyway* and the scores' table."""

    def __init__(
        self,
        gui: viser.GuiApi,
        worker: RenderWorker,
        run: RunView,
        scene: RunScene,
        on_anyway: Callable[[], None],
        scoring: Callable[[], Scoring],
    ) -> None:
        """`scoring()`: what *Score mirrors* scores now (the lesson decides)."""
        self.run, self.scene, self.scoring = run, scene, scoring
        self.frustum_shows = guard_choice(
            gui.add_dropdown(
                "Mirrored frustums show",
                FRUSTUM_IMAGES,
                initial_value=FRUSTUM_IMAGES[0],
                hint="disagreement: |flipped image - the model seen from the mirrored camera|",
            ),
            FRUSTUM_IMAGES,
        )
        self.anyway_btn = gui.add_button(
            "Show the mirrors anyway (not trained on)",
            icon=viser.Icon.EYE,
            visible=False,
            hint="The dropped mirrored cameras, scored and showing where their flipped images disagree",
        )  # shown when mirrors were dropped: by an unconfident estimate at setup, or by the agreement gate
        self.score_btn = gui.add_button("Score mirrors", icon=viser.Icon.RULER, hint="Render each mirrored view now")
        self.table = gui.add_markdown("")
        self.scores: dict[str, list[float]] = {}  # column label -> one PSNR per mirrored view
        self.last_images: ImagesEvent | None = None
        self.worker = worker
        self.score_btn.on_click(lambda _: self.request())
        self.anyway_btn.on_click(lambda _: on_anyway())
        self.frustum_shows.on_update(lambda _: self._show_frustum_images())
        self.clear()

    def request(self) -> None:
        """Score on the render thread, ahead of views waiting there."""
        self.worker.submit("mirror-score", self.score_now, priority=0)

    def clear(self) -> None:
        self.scores, self.last_images = {}, None
        self.table.content = "_Scores appear with the first image event or Score mirrors._"

    def on_images(self, event: ImagesEvent) -> None:
        """Training rendered its (BA-refined) mirrored cameras: score each against its flipped image."""
        if event.mirror_views:
            s = [image_psnr(v.rgb, v.gt) if v.gt is not None else float("nan") for v in event.mirror_views]
            self.scores[f"BA poses, step {event.step}"] = s
            self.scene.set_mirror_colors(s)
            self.last_images = event
            self._show_frustum_images()
            self._show_table([v.name for v in event.mirror_views])

    def _show_frustum_images(self) -> None:
        """The mirrored frustums' images: the flipped image, its disagreement with the model, or beta^2."""
        ev, which = self.last_images, self.frustum_shows.value
        if ev is None or not ev.mirror_views:
            return
        if which == "disagreement":
            imgs = [error_map(v.rgb, v.gt) for v in ev.mirror_views if v.gt is not None]
        elif which == "beta^2" and ev.mirror_views[0].beta2 is not None:
            imgs = [palette.colormap(v.beta2, *palette.BETA2_RANGE) for v in ev.mirror_views]
        else:
            imgs = [to_uint8(v.gt) for v in ev.mirror_views if v.gt is not None]
        self.scene.set_mirror_images(imgs)

    def score_now(self) -> None:
        """Render the model from `scoring()`'s cameras, each scored against its flipped image (render thread)."""
        what = self.scoring()
        scores, disagreement = [], []
        for cam, gt in zip(what.cams, what.flipped):
            out = self.run.render(cam, outputs=("rgb",))
            if out is None or gt is None:
                scores.append(float("nan"))
                disagreement.append(None)
                continue
            rgb, gt = out["rgb"], resize_nearest(gt, out["rgb"].shape[1], out["rgb"].shape[0])
            scores.append(image_psnr(rgb, gt))
            disagreement.append(error_map(rgb, gt))
        if what.preview is None:  # the run's frustums (a dropped one stays grey), and the maps when asked for
            self.scene.set_mirror_colors(scores)
            if self.frustum_shows.value == "disagreement" and scores and all(d is not None for d in disagreement):
                self.scene.set_mirror_images(disagreement)
        else:  # the preview frustums take the colours of their scores (and, asked for, the disagreement maps)
            maps = self.frustum_shows.value == "disagreement"
            what.preview.wear(scores, [d if maps and d is not None else f for d, f in zip(disagreement, what.flipped)])
        self.scores[what.label] = scores  # published once the frustums wear them
        self._show_table(what.names)

    def _show_table(self, names: list[str]) -> None:
        cols = list(self.scores)[-3:]  # the latest three scorings
        head = "| mirrored view | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols) + "\n"
        rows = []
        for i, n in enumerate(names):
            cells = [f"{self.scores[c][i]:.1f} dB" if i < len(self.scores[c]) else "" for c in cols]
            rows.append(f"| {n} | " + " | ".join(cells) + " |")
        means = [np.nanmean(self.scores[c]) if len(self.scores[c]) else float("nan") for c in cols]
        rows.append("| **mean** | " + " | ".join(f"**{m:.1f} dB**" for m in means) + " |")
        lo, hi = palette.SCORE_RANGE
        self.table.content = (
            "Consistency = PSNR of the model seen from each mirrored camera vs its flipped image "
            f"(low = the symmetry assumption fails there). Frustum colours: red {lo:g} dB or less (contradicts), "
            f"yellow {0.5 * (lo + hi):g} dB, green {hi:g} dB or more (agrees).\n\n" + head + "\n".join(rows)
        )
