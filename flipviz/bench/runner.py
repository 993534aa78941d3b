"""Plan the bench's runs, skip the finished ones, execute the rest, then write the reports.

Every run has a key: a hash of its full training configuration (scene, data path, method,
configuration, resolution, steps, seed, flags). Its folder is <out>/runs/<key>/ and it is done
when <out>/runs/<key>/result.json says status "ok"; a killed bench loses only runs in flight.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from flipviz.bench.config import BenchConfig, parse_configs, parse_list, parse_methods
from flipviz.bench.figures import write_figures
from flipviz.bench.local import run_local
from flipviz.bench.ray_cluster import run_ray
from flipviz.bench.report import write_html_report
from flipviz.bench.results import ABLATION, RESULT_FILE, read_result
from flipviz.bench.tables import write_reports
from flipviz.bench.task import RunTask
from flipviz.data import load_scene
from flipviz.data.dataset import DatasetError
from flipviz.data.scenes import SCENES
from flipviz.errors import UserError
from flipviz.files import FolderLock, cannot_write, write_json
from flipviz.options import check_ranges
from flipviz.training.checkpoint import CHECKPOINT_NAME
from flipviz.training.config import TrainConfig, preset_config

# BenchConfig fields that are TrainConfig settings, passed to every run as they are.
RUN_SETTINGS = (
    "res",
    "steps",
    "batch_rays",
    "field",
    "n_samples",
    "grid_res",
    "mirror_plane",
    "mirror_pose",
    "refine_plane",
    "seed",
    "device",
    "preset",
    "unconfident_plane",
    "mirror_disagreement_limit",
    "after_drop",
    "eval_views",
    "eval_tune_steps",
    "eval_every",
)
# TrainConfig fields that change where a run writes or what it logs, not what it computes.
NOT_IN_KEY = (
    "out",
    "rrd",
    "no_rrd",
    "rerun_serve",
    "log_every",
    "images_every",
    "resume",
    "checkpoint_every",
    "eval_on_stop",
    "plane_file",
)


DEFAULTS = TrainConfig().to_dict()
# Settings added after runs were stored, with the value those runs had: in a run's key only away from it, so
# that those runs keep their keys (and the bench skips them) while a run that sets another gets a key of its own.
LATER = ("eval_views", "eval_tune_steps", "eval_every", "lr_end", "entropy_weight", "plane_ramp")
LATER_SETTINGS = {k: DEFAULTS[k] for k in LATER}
LATER_SETTINGS["mirror_disagreement_limit"] = float("inf")  # the gate dropped all mirrors or none before it


def settings_hash(settings: dict) -> str:
    """A run's key's hash: its settings that change its result, written so that a run stored before a
    setting was added, or before a default changed where it cannot matter, is found again."""
    d = {k: v for k, v in settings.items() if k not in NOT_IN_KEY}
    d = {k: v for k, v in d.items() if k not in LATER_SETTINGS or v != LATER_SETTINGS[k]}
    if d["disagreement_limit"] == d.get("mirror_disagreement_limit", float("inf")) == float("inf"):
        d["after_drop"] = "restart"  # no gate, no drop: what follows one cannot matter (its default until 5f89fed)
    return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class RunSpec:
    """One training of the bench. `ba` / `uncertainty` are the TrainConfig flags."""

    scene: str  # the name shown in tables (built-in name or folder name)
    data: str | None  # absolute Blender-format folder, None for a built-in scene
    method: str
    config: int
    ba: bool = True
    uncertainty: bool = True

    def train_config(self, cfg: BenchConfig, out: Path | None = None, planes: Path | None = None) -> TrainConfig:
        """`flipviz train`'s defaults in the bench's preset, with this run's scene, method, configuration
        and flags, and the bench's run settings (BenchConfig's fields named as TrainConfig's). `planes`: the folder
        where the Flip runs of one configuration share their estimated plane (auto)."""
        shared = planes is not None and self.method in ("flip", "flip+u") and cfg.mirror_plane == "auto"
        return preset_config(
            cfg.preset,
            TrainConfig,
            scene=self.scene,
            data=Path(self.data) if self.data else None,
            method=self.method,
            config=self.config,
            ba=self.ba,
            uncertainty=self.uncertainty,
            out=out,
            no_rrd=True,
            images_every=0,  # nobody watches: skip the periodic test renders
            plane_file=planes / self.plane_name(cfg) if shared else None,
            **{k: getattr(cfg, k) for k in RUN_SETTINGS},
        )

    def plane_name(self, cfg: BenchConfig) -> str:
        """The estimate's file: what it depends on (the inputs at the run's resolution, the seed, the device)."""
        d = {"data": self.data, "res": cfg.res, "seed": cfg.seed, "device": cfg.device}
        return (
            f"{self.scene}-c{self.config}-"
            + hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]
            + ".json"
        )

    def key(self, cfg: BenchConfig) -> str:
        return f"{self.scene}-{self.method.replace('+', 'u')}-c{self.config}-" + settings_hash(
            self.train_config(cfg).to_dict()
        )

    def labels(self) -> dict:
        """What the tables need, with the flags the method really uses (e.g. B/L has no BA)."""
        flip = self.method in ("flip", "flip+u")
        return {
            "scene": self.scene,
            "data": self.data or "",
            "method": self.method,
            "config": self.config,
            "ba": flip and self.ba,
            "uncertainty": self.method in ("bl+u", "flip+u") and self.uncertainty,
            "default_flags": self.ba and self.uncertainty,
        }


def resolve_scene(name: str, data_root: Path | None) -> tuple[str, str | None]:
    """(table name, folder or None). Built-in names win; a path, or <data-root>/<name>, is a folder."""
    if name in list(SCENES):
        return name, None
    p = Path(name).expanduser()
    if not (os.sep in name or p.is_dir()):
        if data_root is None:
            raise DatasetError(
                f"scene {name!r} is not built-in ({', '.join(list(SCENES))}); pass --data-root DIR holding {name}/"
            )
        p = Path(data_root).expanduser() / name
    if not (p / "transforms_test.json").is_file():
        raise DatasetError(
            f"scene {name!r}: no transforms_test.json in {p} (the protocol needs the 200-view test orbit)"
        )
    return p.name, str(p.resolve())


def plan(cfg: BenchConfig) -> list[RunSpec]:
    """Every run of the bench, each once, in order scene -> configuration -> method: a configuration's
    B/L first, its Flip after B/L and B/L+U (a Flip run that drops its mirrors takes B/L's finished
    result) and its Flip+U last (by then the plane the Flip runs share is estimated)."""
    check_ranges(cfg)
    methods, configs = parse_methods(cfg.methods), parse_configs(cfg.configs)
    scenes = [resolve_scene(s, cfg.data_root) for s in parse_list(cfg.scenes)]
    if not scenes:
        raise UserError("--scenes is empty")
    RunSpec(*scenes[0], methods[0], configs[0]).train_config(cfg).validate()  # the settings every run shares
    specs: dict[str, RunSpec] = {}
    for scene, data in scenes:
        for n in configs:
            for m in sorted(methods, key=RUN_ORDER.index):
                s = RunSpec(scene, data, m, n)
                specs.setdefault(s.key(cfg), s)
            if cfg.ablation:  # Table II: Flip (no U) / Flip+U, each with and without BA
                for ba, u in ABLATION:
                    s = RunSpec(scene, data, "flip+u" if u else "flip", n, ba=ba)
                    specs.setdefault(s.key(cfg), s)
    return list(specs.values())


RUN_ORDER = ("bl", "bl+u", "flip", "upper", "flip+u")  # a configuration's runs, in the order they start


def twin_of(spec: RunSpec, cfg: BenchConfig) -> RunSpec | None:
    """The B/L run a Flip run repeats exactly when its estimated plane is not confident (see task.py)."""
    if spec.method not in ("flip", "flip+u") or cfg.mirror_plane != "auto":
        return None
    return RunSpec(spec.scene, spec.data, "bl", spec.config)


def _prewarm(specs: list[RunSpec], res: int) -> None:
    """Render each built-in scene once here, so parallel runs share the render cache, not race."""
    for scene in dict.fromkeys(s.scene for s in specs if s.data is None):
        try:
            load_scene(scene, None, res)
        except Exception as e:  # its runs will fail and be recorded; the other scenes go on
            log(f"scene {scene} does not load ({type(e).__name__}: {e}); its runs will fail".splitlines()[0])


def log(msg: str, logfile: Path | None = None) -> None:
    from tqdm import tqdm

    tqdm.write(f"[bench] {msg}", file=sys.stderr)
    if logfile is not None:
        with open(logfile, "a") as f:
            f.write(time.strftime("%Y-%m-%d %H:%M:%S ") + msg + "\n")


def run_bench(cfg: BenchConfig) -> Path:
    """Run (or resume) the bench and write results.csv/json, table.md and the figures in cfg.out;
    one bench at a time per folder (a second one is refused in one line)."""
    check_ranges(cfg)  # every option checked before the folder is made or locked
    specs = [] if cfg.report_only else plan(cfg)
    out = Path(cfg.out).expanduser().resolve()
    lock = FolderLock(out, "bench folder")
    try:
        with cannot_write(out, "the bench's files in"):  # a full disk: one line; runs and checkpoints stay
            return _run_bench_locked(cfg, out, specs)
    finally:
        lock.abandon()  # released; a folder this bench made and wrote nothing in is removed


def _run_bench_locked(cfg: BenchConfig, out: Path, specs: list[RunSpec]) -> Path:
    from tqdm import tqdm

    if cfg.report_only:
        rows = [r for p in sorted((out / "runs").glob("*/" + RESULT_FILE)) if (r := read_result(p.parent))]
        if not rows:
            raise UserError(f"--report-only: no results in {out / 'runs'}")
        write_reports(out, rows, cfg)
        write_figures(out, rows, cfg)
        write_html_report(out, cfg)
        log(f"reports of {len(rows)} runs rebuilt in {out}")
        return out
    (out / "runs").mkdir(parents=True, exist_ok=True)
    logfile = out / "bench.log"
    write_json(out / "bench.json", asdict(cfg))

    keys = [s.key(cfg) for s in specs]
    results: dict[str, dict] = {}
    todo: list[tuple[str, RunSpec]] = []
    for key, spec in zip(keys, specs):
        r = read_result(out / "runs" / key)
        if r is not None and (r.get("status") == "ok" or not cfg.retry_failed):
            results[key] = r
            log(f"skipped {key}: already {r.get('status')} (run {r.get('run_id', '?')[:8]})", logfile)
        else:
            if r is not None and not r.get("died"):  # a failed run is retried from scratch, not from its last
                (out / "runs" / key / CHECKPOINT_NAME).unlink(missing_ok=True)  # checkpoint; a killed one resumes
            todo.append((key, spec))
    log(f"{len(specs)} runs planned: {len(results)} skipped (already done), {len(todo)} to run", logfile)

    if todo:
        _prewarm([s for _, s in todo], cfg.res)
        threads = cfg.cpus_per_run or (max(1, (os.cpu_count() or 1) // cfg.workers) if cfg.executor == "local" else 1)
        tasks = [
            RunTask(
                key=k,
                run_dir=str(out / "runs" / k),
                train=s.train_config(cfg, out / "runs" / k, out / "planes").to_dict(),
                labels=s.labels(),
                threads=threads,
                progress=not cfg.quiet,
                keep_checkpoint=cfg.keep_checkpoints,
                twin=str(out / "runs" / t.key(cfg)) if (t := twin_of(s, cfg)) else "",
            )
            for k, s in todo
        ]
        bar = tqdm(
            total=len(specs),
            initial=len(results),
            desc="bench",
            unit="run",
            position=0,
            dynamic_ncols=True,
            disable=cfg.quiet,
            file=sys.stderr,
        )

        def on_result(res: dict) -> None:
            key = res["key"]
            if res.get("status") == "interrupted":
                log(f"interrupted {key}", logfile)
                return
            if (read_result(out / "runs" / key) or {}).get("run_id") != res.get("run_id"):
                write_json(out / "runs" / key / RESULT_FILE, res)  # e.g. a run on another machine
            results[key] = res
            bar.update(1)
            if res.get("status") == "ok":
                psnr, secs = res.get("psnr") or float("nan"), res.get("train_seconds") or 0.0
                how = (
                    f"taken from {res['reused_from']} (mirrors dropped)"
                    if res.get("reused_from")
                    else f"in {secs:.0f} s"
                )
                log(f"done {key}: PSNR {psnr:.2f} {how}", logfile)
            else:
                log(f"FAILED {key}: {res.get('error', '')}", logfile)

        try:
            if cfg.executor == "ray":
                gpus = 1.0 if cfg.device.startswith("cuda") else 0.0
                run_ray(tasks, cfg.address, cpus_per_run=threads, gpus_per_run=gpus, on_result=on_result)
            else:
                run_local(tasks, cfg.workers, on_result)
        except KeyboardInterrupt:
            bar.close()
            n_ok = sum(r.get("status") == "ok" for r in results.values())
            log(
                f"interrupted: {n_ok} of {len(specs)} runs done; run the same command again to resume (finished "
                "runs are skipped, interrupted ones continue from their checkpoints)",
                logfile,
            )
            raise
        finally:
            bar.close()

    rows = [results[k] for k in keys if k in results]
    write_reports(out, rows, cfg)
    write_figures(out, rows, cfg)
    write_html_report(out, cfg)
    n_ok = sum(r.get("status") == "ok" for r in rows)
    log(f"{n_ok}/{len(specs)} runs ok; reports in {out}", logfile)
    return out
