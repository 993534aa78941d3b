"""What Just Flip changes in a NeRF (paper Sec. IV), read top to bottom in the paper's order.

A plain NeRF step (`Trainer._train_step`) draws random pixels of the training views, casts their
rays from the views' poses, renders them and minimises the squared error plus the field's
regulariser. `Flip` is what Just Flip puts around that step, the way gsplat's strategies sit
around its step: the trainer takes the poses of a step from `Flip.poses()`, its loss from
`Flip.loss()`, and lets `Flip.after_step()` move what Just Flip adds. A run without mirrors (B/L,
Upper, or a Flip run whose estimated plane was dropped) gets the same object with nothing to
move: fixed poses and, after the warm-up, the NLL on its uncertain rays (B/L+U) or the MSE.

IV-A  Mirrored views (`mirrored_views`). Each input image is flipped left-right and posed by
      reflecting its camera through the mirror plane (`--mirror-pose reflect`, the default: exact
      for an object symmetric about that plane, on any trajectory), or by the paper's rule
      (`lookat`: reflect the centre, back onto the least-squares sphere of the input centres, look
      at its centre). The plane is `--mirror-plane` (auto: estimated from the inputs alone,
      training/plane_estimate.py: the run trains its inputs alone for --estimate-after steps,
      the plane is estimated from that field, and the mirrors join at that step, `Flip.start`, with
      the field's learning-rate decay counted again from there: `Flip.field_lr`, --join-lr).
      geometry/mirror.py computes the poses.
      flipviz adds: the plane is a parameter of training (`MirrorPlane`, `--refine-plane`). It has
      3 degrees of freedom, every mirrored camera follows it (c2w(P) = S_P S_P0 c2w_init, a rigid
      motion), and the photometric loss of the mirrored rays moves it. Per-camera BA can only pull
      each camera back on its own; an error all the mirrors share (a plane 1 degree off) makes them
      agree with each other about a ghost, and only the shared parameter can remove it.
IV-B  Bundle adjustment of the mirrored poses (`pose_refiner`, BARF-style, model/pose_refine.py):
      c2w_i = S_P S_P0 c2w_i^init Exp(xi_i) for the mirrored cameras; the inputs stay fixed.
IV-C  Uncertainty (`objective`, model/objective.py): a flipped image is a true view only of a
      symmetric object, so the mirrored rays get a learned variance beta^2 and, after a warm-up
      of plain MSE, the Gaussian NLL: mirrored pixels that contradict the real views weigh less.
          L(r') = ||C(r') - C_hat(r')||^2 / (2 beta_hat^2(r')) + log(beta_hat^2(r')) / 2
                  + (w / N_s) sum_j sigma(t_j)                                         (Eqn. 7)

flipviz adds: the agreement gate (`Agreement`). Each batch compares the mirrored rays' squared
      error on the object with the inputs'; once the NLL is on, the mirrors stop being trained when
      their pooled ratio passes --disagreement-limit (all of them), and a single mirror does when its own
      passes --mirror-disagreement-limit: its rays leave the sampler and its pose freezes where it is,
      while the kept mirrors, their BA and the plane go on. Then (--after-drop) the field goes back to where the
      mirrors joined and trains again without the dropped ones (rollback: what they taught is gone),
      or trains on (continue); restart continues too, but once every mirror is dropped a fresh field
      trains the inputs alone (the run ends as B/L, bit for bit).

The trainer sees `Flip` through a few calls: `poses`, `sample`, `field_lr` and `loss` inside a step,
`after_step` after it (which answers what the trainer must do: go on, build the run again once the
plane is estimated from the field, or roll the field back or restart it after a drop: `Action`), `scalars` and
`live` for its events, `report` for metrics.json, `state_dict` for checkpoints.
Which method uses which part is `methods.py` (B/L+U puts IV-C on the input rays; Upper uses none).
"""

from __future__ import annotations

import copy
import enum
import logging

import numpy as np
import torch
from torch import Tensor, nn

from flipviz.data.cameras import Camera, View
from flipviz.data.dataset import Plane, SceneData
from flipviz.geometry.coverage import coverage
from flipviz.geometry.mirror import MirrorSet, make_mirror_set
from flipviz.geometry.poses import pose_errors
from flipviz.geometry.symmetry import PlaneEstimate, plane_error
from flipviz.model.objective import Objective
from flipviz.model.optim import adam, decay_lr
from flipviz.model.pose_refine import PoseRefiner
from flipviz.model.renderer import ray_box
from flipviz.training.checkpoint import is_count
from flipviz.training.config import FlipConfig
from flipviz.training.methods import MethodSpec, TrainingSet, TrainView
from flipviz.training.pose_tuning import Similarity, test_alignment

log = logging.getLogger("flipviz.training")

AGREEMENT_EMA = 0.05  # weight of a step's batch in the running means (about the last 20 steps)
OBJECT_COLOUR = 0.05  # a target this far from white (any channel) is the object's
MIN_MIRROR_RAYS = 4  # a batch moves a mirror's own running mean when it drew this many of its object rays
PLANE_LR_DECAY = 0.01  # the plane's lr falls 100x over training, as BA's (1e-3 -> 1e-5)
BA_START_WITH_PLANE = 0.5  # FlipConfig.ba_start's default when the plane is refined


# ---------------------------------------------------------------------------------- IV-A: views
def mirrored_views(cfg: FlipConfig, inputs: list[View], scene: SceneData, estimated: Plane | None = None) -> MirrorSet:
    """The flipped inputs with their initial poses (and the exact ones, when the scene's plane is
    known), for cfg.mirror_plane; for "auto", the `estimated` plane (plane_estimate.py)."""
    plane: str | Plane = cfg.mirror_plane
    if plane == "auto":
        plane = estimated if estimated is not None else "opposite"  # no estimate for methods without mirrors
    return make_mirror_set(inputs, plane, scene.symmetry_plane, scene.center, scene.up, pose=cfg.mirror_pose)


def mirrored_train_views(spec: MethodSpec, mirrors: MirrorSet, bbox: np.ndarray) -> list[TrainView]:
    """The mirrored views as training views: refined when BA is on, uncertain under Flip+U. A view
    without a mask (a capture's background) keeps only the rays through the scene box `bbox`: a
    flipped background is not what the mirrored camera would see."""
    return [
        TrainView(
            "mirror",
            v.camera,
            v.rgb,
            spec.ba,
            spec.uncertain_mirrors,
            v.meta.get("source", ""),
            None if v.alpha is not None else rays_through_box(v.camera, bbox),
        )
        for v in mirrors.views
    ]


def rays_through_box(camera: Camera, bbox: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose rays cross the box (2, 3) in front of the camera."""
    o, d = (torch.from_numpy(a) for a in camera.rays())
    t_in, t_out = ray_box(o, d, torch.as_tensor(bbox, dtype=torch.float32))
    return ((t_out > t_in) & (t_out > 0)).numpy().reshape(camera.height, camera.width)


class MirrorPlane(nn.Module):
    """The mirror plane as a parameter: n = normalize(n0 + a u + b v), through p0 + s n0.

    (u, v) span the initial plane, so the tilt (a, b) turns the normal by about |(a, b)| radians
    about the point p0 (the estimate's point nearest the object, or the preset's), and s moves the
    plane along n0 (scene units). All three start at 0: the initial plane P0.
    """

    def __init__(self, plane: Plane, device: torch.device | str = "cpu") -> None:
        super().__init__()
        f32 = dict(dtype=torch.float32, device=device)
        basis = torch.as_tensor(plane.basis(), **f32)  # columns u, v, n0
        self.register_buffer("u", basis[:, 0].contiguous())
        self.register_buffer("v", basis[:, 1].contiguous())
        self.register_buffer("n0", basis[:, 2].contiguous())
        self.register_buffer("p0", torch.as_tensor(plane.point, **f32))
        self.tilt = nn.Parameter(torch.zeros(2, **f32))
        self.shift = nn.Parameter(torch.zeros((), **f32))
        self.register_buffer("S0", self.reflection().detach())  # S_P0

    def normal_offset(self) -> tuple[Tensor, Tensor]:
        """The plane n . x = d: unit normal (3,) and offset ()."""
        n = self.n0 + self.tilt[0] * self.u + self.tilt[1] * self.v
        n = n / n.norm()
        return n, n @ (self.p0 + self.shift * self.n0)

    def reflection(self) -> Tensor:
        """S_P (4, 4): x -> x - 2 (n . x - d) n, the reflection through the plane (det -1)."""
        n, d = self.normal_offset()
        S = torch.eye(4, dtype=n.dtype, device=n.device)
        S[:3, :3] = S[:3, :3] - 2.0 * torch.outer(n, n)
        S[:3, 3] = 2.0 * d * n
        return S

    def motion(self) -> Tensor:
        """S_P S_P0 (4, 4): the rigid motion that takes a camera mirrored through P0 to one mirrored
        through P (the identity at the start). Reflected cameras stay exact reflections; look-at
        ones follow the plane the same way."""
        return self.reflection() @ self.S0

    def plane(self) -> Plane:
        """The current plane, as numpy (its point: the pivot moved along n0, projected onto the plane)."""
        with torch.no_grad():
            n, d = self.normal_offset()
            pivot = self.p0 + self.shift * self.n0
            p = pivot - (pivot @ n - d) * n
        return Plane(p.double().cpu().numpy(), n.double().cpu().numpy())


# ---------------------------------------------------------------------------------- IV-B: BA
def pose_refiner(ts: TrainingSet, steps: int, device: torch.device | str) -> PoseRefiner | None:
    """BA of the views whose refine flag is set (the mirrored ones); None when no pose moves."""
    if not bool(ts.refine_mask.any()):
        return None
    return PoseRefiner(ts.init_c2w, ts.refine_mask, steps, device=device)


# ---------------------------------------------------------------------------------- IV-C: loss
def objective(cfg: FlipConfig, steps: int, beta_min: float, start: int = 0) -> Objective:
    """MSE for the first `uncertainty_start` of the steps from `start` (the step the mirrors join), then
    the NLL on uncertain rays (the density term, with --density-on all, on every ray)."""
    nll_start = start + int(cfg.uncertainty_start * (steps - start))
    return Objective(beta_min, cfg.density_weight, nll_start, cfg.nll_channels, cfg.density_on)


# ---------------------------------------------------------------------------------- agreement
def object_rays(out: dict[str, Tensor], target: Tensor) -> Tensor:
    """(R,) bool: the rays on the object (the target is not the white background, or the render is opaque)."""
    return ((1.0 - target).abs().amax(-1) > OBJECT_COLOUR) | (out["opacity"] > 0.5)


def running_means(old: Tensor, key: Tensor, x: Tensor) -> Tensor:
    """(K,) float64 on the CPU: each key's running mean (EMA, AGREEMENT_EMA) of the values `x` (N,) whose key
    (N,) it is; a batch moves a key's mean when it holds at least MIN_MIRROR_RAYS of them (`old`: NaN until then)."""
    n = len(old)
    sums = torch.zeros(n, dtype=x.dtype, device=x.device).index_add_(0, key, x)  # (K,)
    counts = torch.bincount(key, minlength=n)  # (K,)
    mean = (sums / counts.clamp(min=1)).double().cpu()
    new = torch.where(old.isnan(), mean, (1.0 - AGREEMENT_EMA) * old + AGREEMENT_EMA * mean)
    return torch.where((counts >= MIN_MIRROR_RAYS).cpu(), new, old)


class Agreement:
    """Do the mirrored views agree with the inputs? Measured on the training batches, at no cost.

    On the object's rays (`object_rays`), a
    running mean (EMA, AGREEMENT_EMA per step) of the squared error of the mirrored rays and of
    the input rays, both against the same live field:

        disagreement = EMA(||C - C_hat||^2 | mirrored, object) / EMA(||C - C_hat||^2 | input, object)

    A symmetric object (with a good plane) lets one field fit both, so the ratio falls towards 1
    as training goes on; where the mirrors show what the inputs contradict (a mug's handle, a
    plane far off), the field cannot fit both and the mirrored error stays several times the inputs'.

    Each mirrored view also has its own running mean (`per_mirror`, over the batches that drew at least
    MIN_MIRROR_RAYS of its object rays) and so its own ratio (`ratios`): which mirrors disagree.
    """

    def __init__(self, is_mirror: Tensor) -> None:
        self.is_mirror = is_mirror  # (V,) bool
        self.mirror = self.input = float("nan")
        self.slot = torch.cumsum(is_mirror.long(), 0) - 1  # (V,) a mirrored view's index among the mirrors
        self.per_mirror = torch.full((int(is_mirror.sum()),), float("nan"), dtype=torch.float64)  # (M,)

    def update(self, out: dict[str, Tensor], target: Tensor, view: Tensor) -> None:
        with torch.no_grad():
            sq = (out["rgb"] - target).pow(2).sum(-1)  # (R,)
            obj = object_rays(out, target)  # (R,)
            m = self.is_mirror[view]
            for name, sel in (("mirror", obj & m), ("input", obj & ~m)):
                if bool(sel.any()):
                    x, old = float(sq[sel].mean()), getattr(self, name)
                    setattr(self, name, x if old != old else (1.0 - AGREEMENT_EMA) * old + AGREEMENT_EMA * x)
            sel = obj & m  # each mirror's own running mean, over its object rays in this batch
            self.per_mirror = running_means(self.per_mirror, self.slot[view[sel]], sq[sel])

    @property
    def ratio(self) -> float:
        return self.mirror / self.input if self.input > 0 else float("nan")

    @property
    def ratios(self) -> np.ndarray:
        """(M,) each mirror's ratio: its own running error over the inputs' (NaN until measured)."""
        inp = self.input if self.input > 0 else float("nan")
        return (self.per_mirror / inp).numpy()


# ---------------------------------------------------------------------------------- the hooks
class Action(enum.Enum):
    """What the trainer does after a step (`Flip.after_step`)."""

    GO_ON = "go on"
    JOIN = "join"  # the inputs' warm-up is over: estimate the plane from the field, build the run again around it
    RESTART_FIELD = "restart field"  # the mirrors were dropped: a fresh field on the inputs alone (--after-drop)
    ROLL_BACK = "roll back"  # mirrors were dropped: the field as it was when the mirrors joined (--after-drop)


class Flip:
    """Just Flip around a NeRF step: the poses of a step, its loss, and the parameters it moves
    (BA's xi and the plane), with their own Adam and schedules. Nothing moves without mirrors.

    `start`: the step the mirrored views join (with --mirror-plane auto, once the plane is estimated
    from the run's own field after `warm_up` steps on the inputs alone: --estimate-after); before it only
    the inputs' rays train, and the mirrors' schedules (the NLL's warm-up, BA, the plane) count their
    fractions over the steps from it. `mirrors`: the would-be mirrored views (built for every method);
    `trained`: whether they are trained on (not for B/L, nor when an unconfident plane was dropped)."""

    def __init__(
        self,
        cfg: FlipConfig,
        steps: int,
        ts: TrainingSet,
        mirrors: MirrorSet,
        trained: bool,
        beta_min: float,
        device: torch.device | str,
        start: int = 0,
        warm_up: int = 0,
        estimate: PlaneEstimate | None = None,
        true_plane: Plane | None = None,
    ) -> None:
        self.ts, self.steps, self.start, self.warm_up = ts, steps, start, warm_up
        self.mirrors, self.trained, self.estimate, self.true_plane = mirrors, trained, estimate, true_plane
        self.preset = cfg.mirror_plane
        self.lr_from = start if cfg.join_lr == "restart" else 0  # the step the field's lr decay counts from
        self.after_drop = cfg.after_drop
        span = max(1, steps - start)  # the steps the mirrors train
        self.refiner = pose_refiner(ts, span, device)
        self.refine_inputs = any(v.refine for v in ts.views if v.kind == "input")  # BA of all poses (--refine all)
        self.objective = objective(cfg, steps, beta_min, start)
        self.mirror_ids = torch.as_tensor(ts.mirror_ids, dtype=torch.long, device=device)
        is_mirror = torch.zeros(len(ts.views), dtype=torch.bool, device=device)
        self.agreement = Agreement(is_mirror.index_fill(0, self.mirror_ids, True)) if ts.mirror_ids else None
        refine_plane = cfg.refine_plane and trained and bool(ts.mirror_ids)
        self.plane = MirrorPlane(mirrors.plane, device) if refine_plane else None
        self.plane_start = start + int(cfg.plane_start * span)
        self.plane_ramp = int(cfg.plane_ramp * span)
        ba_start = (
            cfg.ba_start if cfg.ba_start is not None else (BA_START_WITH_PLANE if self.plane is not None else 0.0)
        )
        self.ba_start = start + int(ba_start * span)  # a refined plane moves all the mirrors first
        self.opt_pose = self.refiner.make_optimizer() if self.refiner is not None else None
        self.ba_on = self.refiner is not None and self.ba_start <= start  # poses() uses BA's refined poses
        self.opt_plane = None
        if self.plane is not None:
            self.opt_plane = adam([{"params": list(self.plane.parameters()), "lr": cfg.plane_lr}], 1e-8, (0.9, 0.999))
        self.disagreement_limit, self.mirror_limit = cfg.disagreement_limit, cfg.mirror_disagreement_limit
        self.gate_start = self.objective.nll_start  # the NLL lets mirrors that disagree show it (Agreement)
        self.dropped_at: int | None = None  # the step at which the last mirror stopped being trained
        n_mirrors = len(ts.mirror_ids)
        self.mirror_dropped_at: list[int | None] = [None] * n_mirrors  # each mirror's verdict: the step it left
        self.frozen = torch.eye(4, device=device).repeat(n_mirrors, 1, 1)  # (M, 4, 4) a dropped mirror's pose
        self.kept_rays = int((ts.bank.view < min(ts.mirror_ids)).sum()) if ts.mirror_ids else len(ts.bank)
        self._still: Tensor | None = None  # (V, 4, 4) the poses once every mirror is dropped: nothing moves
        self.rewound = 0  # steps the run went back (--after-drop rollback): the schedules' step is step - rewound
        self._joined = copy.deepcopy(self._moving_state())  # what a rollback returns to: the join's poses, plane

    # -- inside a step
    def sample(self, n: int, generator: torch.Generator, step: int) -> Tensor:
        """(n,) the rays of step `step`: any kept training view's, or, before the mirrors join and once they
        are all dropped, the inputs' (the bank holds the inputs' rays first, then the mirrors')."""
        inputs_only = self.dropped_at is not None or step - self.rewound < self.start
        if inputs_only or not self.n_dropped:
            return self.ts.bank.sample(n, generator, self.kept_rays if inputs_only else None)
        kept = [i for i, v in enumerate(self.ts.views) if v.kind == "input"]
        kept += [m for m, at in zip(self.ts.mirror_ids, self.mirror_dropped_at) if at is None]
        return self.ts.bank.sample_views(n, generator, torch.as_tensor(kept))

    def field_lr(self, field_step: int) -> tuple[int, int]:
        """(step, steps) of the field's learning-rate decay at `field_step`. With --join-lr restart, the
        decay counts again from the step the mirrors joined: the side they bring starts at the full lr, as
        in a run that had them from step 0 (a field restarted after a drop counts from its own start)."""
        if field_step < self.lr_from or (self.dropped_at is not None and self.after_drop != "continue"):
            return field_step, self.steps  # rolled back or restarted with no mirror left: B/L's schedule
        return field_step - self.lr_from, self.steps - self.lr_from

    def poses(self) -> Tensor:
        """(V, 4, 4) the current poses: inputs fixed; mirrors S_P S_P0 c2w_init Exp(xi) (IV-A, IV-B).
        Before BA starts every xi is 0, Exp(xi) the identity and c2w the initial pose: nothing to compute;
        once every mirror is dropped nothing moves: the poses are computed once, without gradients."""
        if self.dropped_at is not None:
            if self._still is None:
                with torch.no_grad():
                    self._still = self._moving_poses()
            return self._still
        return self._moving_poses()

    def _moving_poses(self) -> Tensor:
        c2w = self.refiner() if self.ba_on else self.ts.init_c2w  # c2w_init Exp(xi)
        if self.plane is not None:
            moved = self.plane.motion() @ c2w[self.mirror_ids]  # (M, 4, 4): the mirrors follow the plane
            c2w = c2w.index_copy(0, self.mirror_ids, moved)
        if not self.n_dropped:
            return c2w
        gone = [i for i, at in enumerate(self.mirror_dropped_at) if at is not None]
        return c2w.index_copy(0, self.mirror_ids[gone], self.frozen[gone])  # dropped mirrors stay where they left

    def loss(self, out: dict[str, Tensor], target: Tensor, view: Tensor, step: int) -> Tensor:
        """IV-C on a batch whose rays come from the views `view` (R,); `step`: the field's own step
        (the run's, unless the field was restarted after a drop)."""
        if self.agreement is not None and self.dropped_at is None:  # kept as it was at the drop
            self.agreement.update(out, target, view)
        return self.objective(out, target, self.ts.uncertain[view], step)

    # -- after it
    def after_step(self, step: int) -> Action:
        """Move the poses (BA) and, after its warm-up, the plane by the gradients of step `step` (0-based,
        just taken), and clear them. Once the NLL is on, mirrors that disagree with the inputs are dropped
        (`Agreement`); the answer says what the trainer does next."""
        self.ba_on = self.ba_on or (self.refiner is not None and step + 1 - self.rewound >= self.ba_start)
        action = self._move(step)
        for opt in (self.opt_pose, self.opt_plane):
            if opt is not None:
                opt.zero_grad(set_to_none=True)
        if step + 1 == self.warm_up:
            return Action.JOIN
        return action

    def _move(self, step: int) -> Action:
        s = step - self.rewound  # the schedules' step (a rollback took the run back to the join)
        if s < self.start:
            return Action.GO_ON  # the mirrors have not joined: nothing of theirs moves
        if self.agreement is not None and self.dropped_at is None and s >= self.gate_start:
            leaving = self._disagreeing()
            if leaving:
                return self._drop(leaving, step + 1)
        if self.dropped_at is not None:
            return Action.GO_ON  # nothing mirrored is trained: the poses and the plane stay where they were
        if self.opt_pose is not None and s >= self.ba_start:
            self.refiner.adjust_lr(self.opt_pose, s - self.start)
            self.opt_pose.step()
        if self.opt_plane is not None and s >= self.plane_start:
            decay_lr(self.opt_plane, s - self.plane_start, max(1, self.steps - self.plane_start), PLANE_LR_DECAY)
            if s - self.plane_start < self.plane_ramp:  # lr ramp: lr * (k + 1) / ramp at the k-th step it moves
                for g in self.opt_plane.param_groups:
                    g["lr"] *= (s - self.plane_start + 1) / self.plane_ramp
            self.opt_plane.step()
        return Action.GO_ON

    def _disagreeing(self) -> list[int]:
        """The kept mirrors (indices among the mirrors) to drop: all of them when their pooled ratio is over
        --disagreement-limit, else each whose own is over --mirror-disagreement-limit (one not measured yet
        stays)."""
        kept = [i for i, at in enumerate(self.mirror_dropped_at) if at is None]
        if self.agreement.ratio > self.disagreement_limit:
            return kept
        ratios = self.agreement.ratios
        return [i for i in kept if ratios[i] > self.mirror_limit]

    def _drop(self, leaving: list[int], step: int) -> Action:
        """Mirrors `leaving` stop being trained from step `step` on: their rays leave the sampler, their poses
        freeze where they are. Then the field goes back to the join (rollback), a fresh one trains the inputs
        once no mirror is left (restart), or the field trains on (continue)."""
        with torch.no_grad():
            now = self.poses()[self.mirror_ids].detach()  # (M, 4, 4)
        ratios, pooled = self.agreement.ratios, self.agreement.ratio
        for i in leaving:
            self.mirror_dropped_at[i], self.frozen[i] = step, now[i]
        left = self.n_dropped == len(self.mirror_dropped_at)
        self.dropped_at = step if left else None
        turned = self.plane_turn()
        log.warning(
            "step %d: mirrored views %s disagree with the inputs (their own ratios %s; all kept ones %.2f; limits "
            "%.2f each, %.2f pooled: training/flip.py, Agreement; the plane has turned %.2f deg and moved %.3f "
            "since the join); %s",
            step,
            ", ".join(map(str, leaving)),
            ", ".join(f"{ratios[i]:.2f}" for i in leaving),
            pooled,
            self.mirror_limit,
            self.disagreement_limit,
            *turned,
            "training without any" if left else f"training on with {len(self.mirror_dropped_at) - self.n_dropped}",
        )
        if self.after_drop == "rollback":
            self._roll_back(step)
            return Action.ROLL_BACK
        return Action.RESTART_FIELD if left and self.after_drop == "restart" else Action.GO_ON

    def _roll_back(self, step: int) -> None:
        """From step `step` on, the schedules count again from the join (the trainer's field goes back there
        too, Action.ROLL_BACK): BA's poses, the plane and their optimisers as they were then, the running
        errors measured afresh. The verdicts stay."""
        self._load_moving(copy.deepcopy(self._joined))
        self.ba_on = self.refiner is not None and self.ba_start <= self.start
        self.rewound = step - self.start
        if self.dropped_at is None:  # the kept mirrors are measured again; with none left, the last measure stays
            a = self.agreement
            a.mirror = a.input = float("nan")
            a.per_mirror = torch.full_like(a.per_mirror, float("nan"))

    @property
    def n_dropped(self) -> int:
        return sum(at is not None for at in self.mirror_dropped_at)

    # -- what it shows
    def scalars(self) -> dict[str, float]:
        """The learning rates and, with mirrors, the agreement's errors (a StepEvent's scalars)."""
        agree = {}
        if self.agreement is not None:
            a = self.agreement
            agree = {
                "mse_mirror": a.mirror / 3.0,
                "mse_input": a.input / 3.0,
                "disagreement": a.ratio,
                "mirrors_trained": float(self.dropped_at is None),
                "mirrors_kept": float(len(self.mirror_dropped_at) - self.n_dropped),
            }
        return {**self.lrs(), **agree}

    def lrs(self) -> dict[str, float]:
        return {
            "lr_pose": float(self.opt_pose.param_groups[0]["lr"]) if self.opt_pose is not None else 0.0,
            "lr_plane": float(self.opt_plane.param_groups[0]["lr"]) if self.opt_plane is not None else 0.0,
        }

    def plane_turn(self) -> tuple[float, float]:
        """(degrees, scene units) the refined plane has turned and moved since the join; 0 when not refined."""
        plane = self.current_plane()
        return plane_error(plane, self.mirrors.plane) if plane is not None else (0.0, 0.0)

    def current_plane(self) -> Plane | None:
        """The refined plane (None when the plane is not refined)."""
        return self.plane.plane() if self.plane is not None else None

    def mirror_c2w(self) -> np.ndarray | None:
        """(M, 4, 4) current poses of the mirrored training views; None when none is trained."""
        if not self.ts.mirror_ids:
            return None
        with torch.no_grad():
            return self.poses()[self.mirror_ids].cpu().double().numpy()

    def mirror_cameras(self) -> list[Camera]:
        """The mirrored training cameras at their current (refined) poses."""
        c2w = self.mirror_c2w()
        return [] if c2w is None else [v.camera.with_pose(p) for v, p in zip(self.ts.mirror_views, c2w)]

    def test_alignment(self) -> Similarity:
        """What brings test cameras into the run's frame (pose_tuning.py): the identity unless BA moved the
        inputs too (--refine all), then the mirrors' initial centres to their refined ones."""
        return test_alignment(self.refine_inputs, [v.camera for v in self.ts.mirror_views], self.mirror_c2w())

    def live(self) -> dict:
        """A StepEvent's mirror fields: the mirrored poses now, their change and, where known, their error;
        the refined plane and its error."""
        return self._pose_report() | self._plane_now() | self._verdicts()

    def _verdicts(self) -> dict:
        """Each mirror's disagreement now and the step it was dropped at (StepEvent's fields); {} without mirrors."""
        if self.agreement is None:
            return {}
        return {"mirror_ratio": self.agreement.ratios, "mirror_dropped_at": tuple(self.mirror_dropped_at)}

    def report(self, tests: list[Camera]) -> dict:
        """Flip's part of metrics.json: the mirrors' coverage of the `tests` cameras (every method: B/L rows
        carry what its configuration's mirrors would cover), the plane, the mirrored poses."""
        m: dict = {"coverage": coverage(tests, self.mirrors.cameras, self.mirrors.sphere.center)}
        if self.trained or self.estimate is not None:
            m["plane"] = self._plane_report()
        pose = self._pose_report()
        if pose:
            m["mirror_poses"] = {k: np.asarray(v).tolist() for k, v in pose.items()}
        return m

    def _plane_report(self) -> dict:
        """The mirror plane used, its estimate (auto), and its error against the scene's true plane."""
        rep: dict = {"used": self.mirrors.plane.to_dict(), "preset": self.preset, "trained": self.trained}
        # trained: False when the mirrors were dropped at setup (the estimate's confidence) or by the agreement gate
        if self.estimate is not None:  # not trained: dropped for its confidence (--unconfident-plane)
            rep["confidence"] = self.estimate.confidence
            rep["estimate_seconds"] = self.estimate.seconds
        true = self.true_plane
        if true is not None:
            rep["error_deg"], rep["error_offset"] = plane_error(self.mirrors.plane, true)
        if self.agreement is not None:  # the agreement gate
            rep["disagreement"] = self.agreement.ratio
            rep["disagreement_per_mirror"] = self.agreement.ratios.tolist()  # each mirror's own, same limit
            rep["dropped_at"] = self.dropped_at  # the step the last mirror left
            rep["mirror_dropped_at"] = list(self.mirror_dropped_at)  # each mirror's (None: kept to the end)
            rep["n_mirrors"], rep["kept_mirrors"] = (
                len(self.mirror_dropped_at),
                len(self.mirror_dropped_at) - self.n_dropped,
            )
            rep["after_drop"], rep["rewound_steps"] = self.after_drop, self.rewound
            rep["trained"] = self.dropped_at is None
            restarted = self.dropped_at is not None and self.after_drop == "restart"
            rep["restarted_at"] = self.dropped_at if restarted else None  # the field restarted on the inputs
        refined = self.current_plane()
        if refined is not None:  # --refine-plane: "used" is where the plane started, "refined" where it is now
            rep["refined"] = refined.to_dict()
            rep["refined_change_deg"], rep["refined_change_offset"] = self.plane_turn()
            if true is not None:
                rep["refined_error_deg"], rep["refined_error_offset"] = plane_error(refined, true)
        return rep

    def _plane_now(self) -> dict:
        """The refined plane now and its error where known (StepEvent's plane fields); {} when not refined."""
        plane, true = self.current_plane(), self.true_plane
        if plane is None:
            return {}
        if true is None:
            return {"plane": plane}
        deg, offset = plane_error(plane, true)
        return {"plane": plane, "plane_err_deg": deg, "plane_err_offset": offset}

    def _pose_report(self) -> dict:
        """The mirrored poses now, with their change and, where known, their error."""
        c2w = self.mirror_c2w()
        if c2w is None:
            return {}
        init = [v.camera.c2w for v in self.ts.mirror_views]
        change = np.array([pose_errors(a, b) for a, b in zip(c2w, init)])
        rep: dict = dict(mirror_c2w=c2w, mirror_rot_change_deg=change[:, 0], mirror_trans_change=change[:, 1])
        if self.mirrors.true_cameras is not None:
            err = np.array([pose_errors(a, t.c2w) for a, t in zip(c2w, self.mirrors.true_cameras)])
            rep.update(mirror_rot_err_deg=err[:, 0], mirror_trans_err=err[:, 1])
        return rep

    # -- checkpoints
    def _moving_state(self) -> dict:
        """BA's poses, the plane and their optimisers (what a rollback restores)."""
        parts = {"poses": self.refiner, "opt_pose": self.opt_pose, "plane": self.plane, "opt_plane": self.opt_plane}
        return {key: obj.state_dict() if obj is not None else None for key, obj in parts.items()}

    def _load_moving(self, state: dict) -> None:
        parts = {"poses": self.refiner, "opt_pose": self.opt_pose, "plane": self.plane, "opt_plane": self.opt_plane}
        for key, obj in parts.items():
            if obj is not None and state.get(key) is not None:
                obj.load_state_dict(state[key])
        self._still = None  # the poses moved (a rollback, a checkpoint): poses() computes them again

    def state_dict(self) -> dict:
        return {
            **self._moving_state(),
            "ba_on": self.ba_on,
            "agreement": {
                "mirror": a.mirror,
                "input": a.input,
                "per_mirror": a.per_mirror.tolist(),
                "dropped_at": self.dropped_at,
                "mirror_dropped_at": list(self.mirror_dropped_at),
                "frozen": self.frozen.cpu(),
                "rewound": self.rewound,
            }
            if (a := self.agreement)
            else None,
        }

    @property
    def field_restarted(self) -> bool:
        """A fresh field (no variance head) trains the inputs: every mirror dropped under --after-drop restart."""
        return self.dropped_at is not None and self.after_drop == "restart"

    def load_state_dict(self, state: dict) -> None:
        """What `state_dict` wrote (a checkpoint from before the plane was refined has no plane: it stays P0)."""
        self._load_moving(state)
        moved = self.refiner is not None and bool(self.refiner.xi.detach().abs().sum() > 0)
        saved = state.get("ba_on")  # saved since poses() computes BA's poses only once it is on
        self.ba_on = self.ba_on or (saved if isinstance(saved, bool) else moved)
        agree = state.get("agreement")
        if self.agreement is not None and isinstance(agree, dict):
            self.agreement.mirror, self.agreement.input = float(agree["mirror"]), float(agree["input"])
            each = agree.get("per_mirror")  # absent in checkpoints written before it was measured
            if each is not None:
                each = torch.as_tensor(each, dtype=torch.float64)
                if each.shape != self.agreement.per_mirror.shape:
                    raise ValueError(f"{len(each)} mirrors' agreement for {len(self.agreement.per_mirror)} mirrors")
                self.agreement.per_mirror = each
            dropped = agree.get("dropped_at")
            if dropped is not None and not is_count(dropped):
                raise ValueError(f"dropped_at {dropped!r} is not a step")
            self.dropped_at = dropped
            n = len(self.mirror_dropped_at)  # checkpoints from before per-mirror verdicts: all or none
            each = agree.get("mirror_dropped_at", [dropped] * n)
            if not isinstance(each, list) or len(each) != n or not all(at is None or is_count(at) for at in each):
                raise ValueError(f"mirror_dropped_at {each!r} is not a step or None for each of {n} mirrors")
            frozen = agree.get("frozen")
            if frozen is not None:
                self.frozen = torch.as_tensor(frozen, dtype=torch.float32).to(self.frozen.device).reshape(n, 4, 4)
            elif any(at is not None for at in each):  # an old checkpoint: they stopped where its poses are
                with torch.no_grad():
                    self.frozen = self._moving_poses()[self.mirror_ids].detach()
            self.mirror_dropped_at = list(each)
            rewound = agree.get("rewound", 0)
            if not is_count(rewound):
                raise ValueError(f"rewound {rewound!r} is not a step count")
            self.rewound = rewound
