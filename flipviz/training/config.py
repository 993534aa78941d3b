"""Run configuration, used by the CLI (tyro), the app and the benchmark.

`TrainConfig` holds a run's method and preset and four settings by concern: `data` (what it trains on),
`engine` (how it optimises and renders), `flip` (what Just Flip adds) and `output` (what it writes). The
command line keeps one flat flag per setting (`--steps`, `--plane-lr`); in code, `cfg.engine.steps`.
Saved runs (checkpoint.pt, metrics.json) keep the flat settings by those flag names:
`TrainConfig.from_settings(**cfg.to_dict())` is `cfg` again."""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Annotated, Literal, TypeVar

import tyro

from flipviz.errors import UserError
from flipviz.options import Range, check_ranges

Method = Literal["bl", "bl+u", "flip", "flip+u", "upper"]
METHODS: tuple[str, ...] = ("bl", "bl+u", "flip", "flip+u", "upper")
METHOD_LABELS: dict[str, str] = {"bl": "B/L", "bl+u": "B/L+U", "flip": "Flip", "flip+u": "Flip+U", "upper": "Upper"}


def check_device(device: str) -> None:
    """`device` names a torch device this machine has: cpu, cuda or cuda:N (when CUDA is there)."""
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device!r} is not a device; use cpu, cuda or cuda:N") from None
    if dev.type == "cpu":
        return
    if dev.type != "cuda":
        raise UserError(f"--device {device!r} is not supported; use cpu, cuda or cuda:N")
    if not torch.cuda.is_available():
        raise UserError(
            f"--device {device!r}: no CUDA device is available here (torch {torch.__version__}); use --device cpu"
        )
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise UserError(f"--device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")


def fits(value: object, hint: object) -> bool:
    """`value` is of the annotated type `hint`: Literal, X | None, tuple[int, ...], int (not a bool),
    float (an int too), bool, str, Path (or its str, as saved in a checkpoint)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        return any(type(value) is type(a) and value == a for a in args)
    if origin in (typing.Union, types.UnionType):
        return any(fits(value, a) for a in args)
    if origin is tuple:
        return isinstance(value, (tuple, list)) and all(fits(v, args[0]) for v in value)
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is Path:
        return isinstance(value, (str, Path))
    return isinstance(value, hint)  # bool, str


def type_words(hint: object) -> str:
    """The annotated type `hint` in words, for an error line."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_words(a) for a in args)
    if origin is tuple:
        return f"a list of {type_words(args[0]).removeprefix('a ')}s"
    words = {
        type(None): "none",
        float: "a number",
        int: "a whole number",
        bool: "true or false",
        str: "text",
        Path: "a path",
    }
    return words.get(hint, getattr(hint, "__name__", str(hint)))


# The settings the bench shares with a run, each with its bounds (flipviz/options.py), stated once
Res = Annotated[int, Range(8, 1024)]
Steps = Annotated[int, Range(1, 10_000_000)]
BatchRays = Annotated[int, Range(1, 1_000_000)]
Samples = Annotated[int, Range(2, 1024)]
GridRes = Annotated[tuple[int, ...] | None, Range(8, 512)]
Seed = Annotated[int, Range(0, 2**63 - 1)]
EvalSteps = Annotated[int, Range(0, 10_000)]
EvalEvery = Annotated[int, Range(1, 1000)]


@dataclass
class DataConfig:
    """What a run trains and is scored on: the scene, its protocol configuration, the image size."""

    scene: str = "chair"
    """Built-in scene name (ignored when --data is given)."""
    path: Annotated[Path | None, tyro.conf.arg(name="data")] = None
    """A scene folder: a Blender orbit (transforms_test.json, e.g. NeRF-synthetic), a nerfstudio capture
    (transforms.json) or a COLMAP capture (images/ + sparse/0)."""
    inputs: str = ""
    """Protocol-free runs: the input frames, '' (a capture's train split, else all), 'all', '0,3,5-9' or
    'az:-60..120' (azimuth range, degrees); the other frames (or the capture's test split) are evaluated.
    Orbit scenes without it use the protocol's --config."""
    config: Annotated[int, Range(1, 8)] = 1
    """Protocol configuration n = 1..8 (which half ring is observed)."""
    res: Res = 100
    """Image width in pixels (images are square), 8..1024; at most the data's own width."""


@dataclass
class EngineConfig:
    """How a run optimises and renders, whatever its method: steps, rays, field, samples, device."""

    steps: Steps = 600
    """Optimisation steps, 1..10,000,000."""
    batch_rays: BatchRays = 1024
    """Rays per step, 1..1,000,000."""
    field: Literal["grid", "nerf"] = "grid"
    """grid: fast dense voxel grid (default); nerf: vanilla NeRF MLP, the paper's setting."""
    n_samples: Samples = 64
    """Samples per ray, in training and rendering, 2..1024 (why 64: docs/METHOD.md#defaults)."""
    grid_res: GridRes = None
    """Grid field: voxels along the longest side, coarse to fine (None: the field's default)."""
    background: Literal["white", "learned", "last"] = "white"
    """What a ray's left-over transmittance sees (model/renderer.py): white (the datasets' background:
    space no view saw stays white), learned (one RGB colour, trained), or last (the official code: the
    field's colour at the ray's far end, so space no view saw shows whatever the field holds: fog)."""
    seed: Seed = 0
    """Seed of the run (torch, the ray sampler, the estimate's search)."""
    lr_end: Annotated[float | None, Range(1e-6, 1.0)] = None
    """The field's learning rates decay exponentially to this fraction of their start (None: the field's
    own, 0.1; the paper's NeRF: 0.2, BARF's 5e-4 -> 1e-4)."""
    entropy_weight: Annotated[float, Range(0.0, 1e3)] = 1e-3
    """Weight of the opacity-entropy regulariser that clears white fog (DVGO's; the paper's NeRF has none)."""
    device: str = "cpu"
    """cpu | cuda | cuda:N."""


@dataclass
class FlipConfig:
    """What Just Flip adds (training/flip.py): the mirror plane and the mirrored poses, their refinement, the
    agreement gate, and the learned variance beta^2 (the uncertainty loss; B/L+U uses it too)."""

    mirror_plane: str = "auto"
    """auto (estimated from the inputs, with a confidence) | opposite | official (x = 0) | scene (the
    built-in's true plane) | 'px,py,pz;nx,ny,nz' (a point and a normal)."""
    mirror_pose: Literal["reflect", "lookat"] = "reflect"
    """Initial mirrored poses: reflect (each camera reflected whole through the plane: exact for an object
    symmetric about it, on any trajectory) or lookat (the paper: reflect the centre, back onto the sphere, look
    at its centre). docs/METHOD.md#defaults."""
    plane_file: Path | None = None
    """With --mirror-plane auto: read the estimate from this plane.json when it exists (another run's on
    the same inputs, e.g. Flip beside Flip+U), else estimate it and write it there as well."""
    estimate_after: Annotated[int, Range(0, 10_000_000)] = 150
    """With --mirror-plane auto and the grid field: the steps the inputs train alone before the plane is
    estimated from the run's own field and the mirrored views join (their schedules count from there); 0, a
    short run or --field nerf: a separate short fit estimates it first. docs/METHOD.md#defaults."""
    join_lr: Literal["restart", "continue"] = "restart"
    """When the mirrored views join after --estimate-after: the field's learning-rate decay restarts there,
    or continues. docs/METHOD.md#defaults."""
    unconfident_plane: Literal["drop", "use"] = "use"
    """With --mirror-plane auto and an estimate that is not confident: use (train its mirrors; the agreement
    gate drops them if they disagree with the inputs) or drop (train on the inputs only, as B/L)."""
    disagreement_limit: Annotated[float, Range(1.0, float("inf"))] = 3.25
    """Flip methods, once the NLL is on: every kept mirrored view is dropped when their pooled squared error
    on the object exceeds this many times the inputs' (training/flip.py: Agreement); inf: never.
    docs/METHOD.md#defaults."""
    mirror_disagreement_limit: Annotated[float, Range(1.0, float("inf"))] = 6.0
    """Flip methods, once the NLL is on: one mirrored view is dropped (its rays leave the sampler, its pose
    freezes) when its own squared error on the object exceeds this many times the inputs'; inf: never."""
    after_drop: Literal["rollback", "restart", "continue"] = "rollback"
    """When the gate drops mirrors: rollback (the field, optimiser, poses and plane go back to the join and
    train again without them), restart (once all are dropped, a fresh field trains the inputs alone) or
    continue (what they taught stays). docs/METHOD.md#defaults."""
    refine_plane: bool = True
    """Flip methods: the mirror plane is a parameter of training (training/flip.py: MirrorPlane); the
    mirrored cameras follow it and the mirrored rays' photometric loss moves it."""
    plane_lr: Annotated[float, Range(0.0, 1.0)] = 1e-2
    """The plane's Adam learning rate (radians of tilt, scene units of shift per step), decaying 100x."""
    plane_start: Annotated[float, Range(0.0, 1.0)] = 0.0
    """Fraction of the steps before the plane starts to move (its warm-up)."""
    plane_ramp: Annotated[float, Range(0.0, 1.0)] = 0.0
    """Fraction of the steps over which the plane's learning rate rises linearly from 0 once it moves (Adam's
    first steps are full-size whatever the gradient); 0: none."""
    ba: bool = True
    """Bundle-adjust the mirrored poses (Flip methods)."""
    ba_start: Annotated[float | None, Range(0.0, 1.0)] = None
    """Fraction of the steps before BA moves the mirrored poses; None: 0.5 when the plane is refined (so BA
    does not absorb the plane's error camera by camera), else 0 (BARF's). docs/METHOD.md#defaults."""
    refine: Literal["mirrored", "all"] = "mirrored"
    """Which poses BA refines (Flip methods): the mirrored ones (the paper's text), or all (the code's)."""
    uncertainty: bool = True
    """Learned beta^2 on mirrored rays (Flip+U; --no-uncertainty gives the Table II ablation)."""
    uncertainty_start: Annotated[float, Range(0.0, 1.0)] = 0.2
    """Fraction of the steps trained with plain MSE before the uncertainty loss starts (paper: 10k of 50k)."""
    density_weight: Annotated[float, Range(0.0, 1e6)] = 0.01
    """w of the density regulariser (w / N_s) sum sigma in the uncertainty loss (paper Sec. IV-C)."""
    beta2_mode: Literal["linear", "variance"] = "linear"
    """How the per-sample variances composite into beta_hat^2 (see flipviz/model/renderer.py)."""
    density_on: Literal["uncertain", "all"] = "uncertain"
    """The NLL's density term (w / N_s) sum sigma: on the uncertain rays (the paper's Eqn. 7), or on every
    ray once the NLL starts, B/L's included (the official code)."""
    nll_channels: Literal["sum", "mean"] = "sum"
    """The NLL's ||C - C_hat||^2: summed over RGB (the paper's norm), or averaged (the official code: the
    optimal beta^2 is a third of the sum's, so mirrored rays weigh 3x more)."""
    beta_from: Literal["colour", "position"] = "colour"
    """The variance head: on the colour branch (position and view direction), or on the position
    features alone (the official code: from the density trunk)."""


@dataclass
class EvalConfig:
    """How a run is scored at its end: on which views, and whether each test pose is first tuned on its own
    ground truth. flipviz's protocol scores the 8 unobserved views at their poses; the authors' (the
    released code: `--eval-views orbit --eval-tune-steps 100`) looks at the test images (pose_tuning.py)."""

    eval_views: Literal["unobserved", "orbit"] = "unobserved"
    """unobserved: the protocol's 8 test views; orbit: every view of the orbit the run did not train on (the
    released code scores all of transforms_test.json; lego: 192 of its 200 views, the 8 inputs left out;
    a built-in's first turn: 92 of 100). A capture scores its held-out frames either way."""
    eval_tune_steps: EvalSteps = 0
    """Adam steps that tune each test pose on its ground truth before it is scored (the released code: 100;
    lr 1e-3, 1024 random pixels a step, after aligning the test cameras to the refined mirrored ones when
    BA moved the inputs too). 0: each view is scored at its given pose."""
    eval_every: EvalEvery = 1
    """Score every n-th of those views (1: all). Tuning 192 lego views takes 10-20 min on one CPU thread:
    the budget study scores every 4th (studies/study_table3.py)."""

    def words(self) -> str:
        """The protocol these settings score in, as every table and status line names it."""
        every = f"every {ordinal(self.eval_every)} of " if self.eval_every > 1 else ""  # --eval-every n: a sample
        if self.eval_views == "unobserved":
            views = f"{every}the 8 unobserved views"
        elif every:
            views = f"{every}the orbit views a run did not train on"
        else:
            views = "every orbit view a run did not train on"
        if self.eval_tune_steps == 0:
            return f"flipviz's protocol ({views}, at their poses)" if self.eval_views == "unobserved" else views
        return f"the authors' protocol ({views}, each pose tuned {self.eval_tune_steps} steps on its ground truth)"


def ordinal(n: int) -> str:
    """2nd, 3rd, 4th, 11th, 21st: the English ordinal of n."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


@dataclass
class OutputConfig:
    """Where a run writes and what it reads back: its folder, checkpoints, events, Rerun recording."""

    out: Path | None = None
    """Run folder (default runs/<scene>-<method>-<config>-<time>)."""
    resume: Path | None = None
    """Resume from a checkpoint file (or a run folder holding checkpoint.pt)."""
    overwrite: bool = False
    """Train afresh into an --out that holds an earlier run, deleting its checkpoint, metrics,
    renders and recordings first (without it, such a folder is refused unless --resume)."""
    log_every: Annotated[int, Range(1, 10_000_000)] = 10
    """Steps between StepEvents (>= 1)."""
    images_every: Annotated[int, Range(0, 10_000_000)] = 250
    """Steps between ImagesEvents (test renders and beta^2 maps); 0: none."""
    checkpoint_every: Annotated[int, Range(0, 10_000_000)] = 500
    """Steps between checkpoints (atomic; a non-finite state is never written); 0: only at the end."""
    eval_on_stop: bool = True
    """Evaluate the test views also when a run is stopped early by Ctrl-C (a stop() from the app, a restart,
    skips it: nothing waits for an evaluation)."""
    rrd: Path | None = None
    """Rerun recording path (default <run folder>/recording.rrd)."""
    no_rrd: bool = False
    """Do not write a Rerun recording."""
    rerun_serve: bool = False
    """Also stream to a local Rerun web viewer (bound to 127.0.0.1) and print its URL."""


FlatFlags = tyro.conf.OmitArgPrefixes  # a nested config whose flags carry no prefix
GROUPS = {"data": DataConfig, "engine": EngineConfig, "flip": FlipConfig, "eval": EvalConfig, "output": OutputConfig}


def flag_name(cls: type, name: str) -> str:
    """The flat setting (and flag) a group's field is known by: its name, or its tyro.conf.arg name."""
    hint = typing.get_type_hints(cls, include_extras=True)[name]
    return next((m.name for m in getattr(hint, "__metadata__", ()) if getattr(m, "name", None)), name)


# flat setting name -> (group, field): "steps" -> ("engine", "steps"), "data" -> ("data", "path")
SETTINGS: dict[str, tuple[str, str]] = {
    flag_name(cls, f.name): (group, f.name) for group, cls in GROUPS.items() for f in fields(cls)
}
# flat setting name -> its type, which `TrainConfig.validate` checks each value against
HINTS: dict[str, object] = {k: typing.get_type_hints(GROUPS[group])[name] for k, (group, name) in SETTINGS.items()}


@dataclass
class TrainConfig:
    """One training run of one method on one protocol configuration."""

    method: Method = "flip+u"
    """bl | bl+u | flip | flip+u | upper (the paper's five methods)."""
    preset: Literal["fast", "authors", "paper"] = "fast"
    """fast: flipviz's defaults (the grid field, the settings below); authors: the official code's choices
    on the fast grid (--background last, --density-on all, --nll-channels mean, --beta-from position,
    --refine all, --mirror-pose lookat, --no-refine-plane; the code's plane is x = 0: add --mirror-plane
    official); paper: those and the paper's vanilla NeRF (--field nerf, 128 samples, 50k steps, the NLL
    from 10k, lr 5e-4 -> 1e-4, no entropy term), for a GPU. On the command line every setting you pass
    wins over the preset's, whatever its value (docs/AUTHORS_SETTING.md). In code, build a preset's
    config with `preset_config(name, ...)`: this field alone only names it."""

    # each group's settings keep flat flags (--steps, not --engine.steps): FlatFlags
    data: FlatFlags[DataConfig] = field(default_factory=DataConfig)
    engine: FlatFlags[EngineConfig] = field(default_factory=EngineConfig)
    flip: FlatFlags[FlipConfig] = field(default_factory=FlipConfig)
    eval: FlatFlags[EvalConfig] = field(default_factory=EvalConfig)
    output: FlatFlags[OutputConfig] = field(default_factory=OutputConfig)

    @classmethod
    def from_settings(cls: type[T], **settings: object) -> T:
        """`cls`'s defaults with flat settings over them, by their flag names (`steps=50`, `data=folder`)."""
        return cls().with_settings(**settings)

    def with_settings(self: T, **settings: object) -> T:
        """A copy with flat settings changed, by their flag names (as `dataclasses.replace` by field names)."""
        top = {f.name for f in fields(self)} - set(GROUPS)
        unknown = set(settings) - top - set(SETTINGS)
        if unknown:
            raise TypeError(f"{type(self).__name__} has no setting {', '.join(sorted(unknown))}")
        changes: dict[str, dict[str, object]] = {g: {} for g in GROUPS}
        for k, v in settings.items():
            if k in SETTINGS:
                changes[SETTINGS[k][0]][SETTINGS[k][1]] = v
        groups = {g: replace(getattr(self, g), **c) for g, c in changes.items()}  # each a copy: none shared
        return replace(self, **{k: v for k, v in settings.items() if k in top}, **groups)

    def settings(self) -> dict[str, object]:
        """Every TrainConfig setting, flat, by its flag name (an app's or bench's own fields left out)."""
        flat: dict[str, object] = {"method": self.method, "preset": self.preset}
        return flat | {k: getattr(getattr(self, g), name) for k, (g, name) in SETTINGS.items()}

    def validate(self: T) -> T:
        """Every setting of its type and within its stated limits, else one `UserError` line; train,
        app and bench call it, and so does every run read back from a checkpoint."""
        hints = HINTS | {"method": Method, "preset": typing.get_type_hints(TrainConfig)["preset"]}
        settings = self.settings()
        for name, value in settings.items():  # the app's config adds its own fields, which tyro checked
            if not fits(value, hints[name]):
                raise UserError(f"--{name.replace('_', '-')} must be {type_words(hints[name])}, got {value!r}")
        check_ranges(self)  # each numeric setting within the Range beside it
        flip = self.flip
        if flip.plane_file is not None and Path(flip.plane_file).exists() and not Path(flip.plane_file).is_file():
            raise UserError(f"--plane-file {flip.plane_file} is not a file (it is read, or written after the estimate)")
        if self.engine.grid_res == ():
            raise UserError("--grid-res needs at least one resolution")
        from flipviz.geometry.mirror import PRESETS as PLANE_PRESETS
        from flipviz.geometry.mirror import parse_plane

        if flip.mirror_plane.strip().lower() not in ("auto", *PLANE_PRESETS):
            parse_plane(flip.mirror_plane)  # one line when it is neither a preset nor 'px,py,pz;nx,ny,nz'
        check_device(self.engine.device)
        return self

    def to_dict(self) -> dict:
        """The flat settings as saved (checkpoint.pt, metrics.json): paths as text."""
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in self.settings().items()}


T = TypeVar("T", bound=TrainConfig)
C = TypeVar("C")

# --preset, as whole configs; `preset` itself is only their label. fast: flipviz's defaults. authors: where
# the official code (minjae-lulu/Just-Flip) differs from the paper's text and from flipviz, its choice, on
# the fast grid (docs/AUTHORS_SETTING.md gives each with its file and line). paper: those and the paper's
# setting (Sec. V-A: vanilla NeRF, one network sampling 128 points, 50k iterations, the uncertainty from
# 10k on; BARF's NeRF for the rest: 1024 rays a step, lr 5e-4 -> 1e-4, no entropy term), for a GPU.
FAST = TrainConfig()
AUTHORS = FAST.with_settings(
    preset="authors", background="last", density_on="all", nll_channels="mean", beta_from="position",
    refine="all", mirror_pose="lookat", refine_plane=False, disagreement_limit=float("inf"),
    mirror_disagreement_limit=float("inf"),
)  # fmt: skip
PAPER = AUTHORS.with_settings(
    preset="paper", field="nerf", n_samples=128, steps=50_000, uncertainty_start=0.2, batch_rays=1024,
    lr_end=0.2, entropy_weight=0.0,
)  # fmt: skip
PRESETS: dict[str, TrainConfig] = {"fast": FAST, "authors": AUTHORS, "paper": PAPER}


def preset_changes(name: str) -> dict[str, object]:
    """The settings in which preset `name` differs from flipviz's defaults."""
    fast, mine = FAST.settings(), PRESETS[name].settings()
    return {k: v for k, v in mine.items() if v != fast[k] and k != "preset"}


def settings_of(cfg: object) -> dict[str, object]:
    """A config's flat settings: a TrainConfig's (and its subclass's own fields), or a flat dataclass's."""
    own = {f.name: getattr(cfg, f.name) for f in fields(cfg) if f.name not in GROUPS}
    return own | cfg.settings() if isinstance(cfg, TrainConfig) else own


def with_settings(cfg: C, **settings: object) -> C:
    """`cfg` with flat settings changed: a TrainConfig's by flag name, a flat dataclass's by field name."""
    return cfg.with_settings(**settings) if isinstance(cfg, TrainConfig) else replace(cfg, **settings)


def preset_config(name: str, cls: type[C] = TrainConfig, **settings: object) -> C:
    """The preset `name` as a config of `cls` (TrainConfig, the app's or the bench's): `cls`'s defaults,
    the preset's settings over them (those `cls` has), then `settings` (yours) over both. The CLI
    parses with this as its defaults, so an option you pass wins whatever its value."""
    base = cls()
    chosen = {k: v for k, v in preset_changes(name).items() if k in settings_of(base)}
    return with_settings(base, **{**chosen, **settings, "preset": name})


def with_preset(cfg: C, preset: str) -> C:
    """`cfg` in another preset: each setting still at the old preset's value takes the new preset's; a
    setting you changed from it stays (as on the command line)."""
    if preset == cfg.preset:
        return cfg
    old, new = (settings_of(preset_config(p, type(cfg))) for p in (cfg.preset, preset))
    mine = settings_of(cfg)
    names = {k for p in PRESETS for k in preset_changes(p) if k in mine}
    return with_settings(cfg, **{k: new[k] for k in names if mine[k] == old[k]}, preset=preset)
