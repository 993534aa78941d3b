"""One bench run as plain data (`RunTask`), and `execute_run`, which trains it wherever it runs.

`execute_run` trains the task, scores the unobserved views, writes `<run_dir>/result.json`
atomically and returns the result. Exceptions become a "failed" result with the error, so one
crash never stops the other runs. Where tasks run: `local.py` (processes), `ray_cluster.py`.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import sys
import time
import traceback
import uuid
from dataclasses import dataclass
from pathlib import Path

from flipviz.bench.results import RESULT_FILE, STARTED_FILE, read_json, read_result
from flipviz.files import write_json
from flipviz.training.checkpoint import CHECKPOINT_NAME

SHIP_SUFFIXES = (".json", ".png", ".csv", ".txt")  # what a remote run sends back (no checkpoints)
SHIP_MAX_BYTES = 32 << 20


@dataclass
class RunTask:
    key: str
    run_dir: str
    train: dict  # TrainConfig fields (plain data)
    labels: dict  # scene / method / config / ba / uncertainty as the tables use them
    threads: int = 1
    progress: bool = True
    ship_files: bool = False  # return small output files (for runs on another machine)
    slot: int = 0  # per-run progress-bar row
    keep_checkpoint: bool = False  # else checkpoint.pt is deleted once the result is written
    twin: str = ""  # Flip runs: the run folder of the B/L run they repeat exactly if they drop their mirrors


def versions() -> dict[str, str]:
    import numpy
    import torch

    try:
        from importlib.metadata import version

        fv = version("flipviz")
    except Exception:  # a source checkout that is not pip-installed: read pyproject.toml
        pp = Path(__file__).resolve().parents[2] / "pyproject.toml"
        m = re.search(r'^version\s*=\s*"([^"]+)"', pp.read_text(), re.M) if pp.is_file() else None
        fv = m.group(1) if m else "unknown"
    return {"flipviz": fv, "torch": torch.__version__, "numpy": numpy.__version__}


# ------------------------------------------------------------------------------ one run


def _progress_observer(task: RunTask):
    """A per-run progress bar on the worker's own row (ray's tqdm inside a Ray worker, so the driver draws it)."""
    from flipviz.training.progress import ProgressObserver

    lab = task.labels
    label = (
        lab["method"]
        if lab.get("default_flags", True)
        else (f"{lab['method']} (ba={int(lab['ba'])},u={int(lab['uncertainty'])})")
    )
    if _inside_ray_worker():
        from ray.experimental.tqdm_ray import tqdm as ray_tqdm

        return ProgressObserver(label=label, bar_cls=ray_tqdm)
    return ProgressObserver(label=label, position=task.slot + 1, leave=False)


def _inside_ray_worker() -> bool:
    if "ray" not in sys.modules:
        return False
    import ray

    return ray.is_initialized() and ray.get_runtime_context().worker.mode == ray.WORKER_MODE


def execute_run(task: RunTask | dict) -> dict:
    """Train one run, write <run_dir>/result.json atomically, return the result (never raises)."""
    if isinstance(task, dict):
        task = RunTask(**task)
    import torch

    torch.set_num_threads(max(1, task.threads))
    run_dir = Path(task.run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError:  # a Ray worker on another machine: work in a temporary folder, ship the files
        if not task.ship_files:
            raise
        import tempfile

        run_dir = Path(tempfile.mkdtemp(prefix=f"flipviz-{task.key}-"))
        task.train = task.train | {"out": str(run_dir)}
    earlier = earlier_wall_seconds(run_dir)  # (read before this attempt's started.json replaces the last one's)
    started = time.time()
    run_id = uuid.uuid4().hex
    host = os.uname().nodename
    write_json(
        run_dir / STARTED_FILE,
        {"run_id": run_id, "started": started, "pid": os.getpid(), "host": host, "earlier_wall_seconds": earlier},
    )
    result = {
        "key": task.key,
        "run_id": run_id,
        **task.labels,
        "status": "failed",
        "error": "",
        "psnr": None,
        "ssim": None,
        "lpips": None,
        "train_seconds": None,
        "steps": None,
        "started": started,
        "finished": None,
        "threads": task.threads,
        "host": host,
        "train_config": task.train,
    }
    try:
        result["versions"] = versions()
        from flipviz.training.run import make_trainer
        from flipviz.training.saved_run import run_config

        trainer = make_trainer(run_config(task.train), resume_unfinished=True)
        result["resumed_from_step"] = trainer.step  # > 0: it went on from the checkpoint of a stopped or killed run
        twin = _finished_twin(task, trainer)
        if twin is not None:
            metrics = _reuse_twin(trainer, Path(task.twin), twin)
            result["reused_from"] = twin["key"]
        else:
            if task.progress:
                trainer.add_observer(_progress_observer(task))
            metrics = trainer.run()  # Ctrl-C inside the loop ends it with status "stopped"
        status = metrics["status"]
        ok = status == "finished"
        lpips = metrics.get("lpips")
        if status == "stopped":  # Ctrl-C: not a result; the restart resumes from the checkpoint
            return result | {"status": "interrupted", "error": "interrupted"}
        result.update(
            status="ok" if ok else "failed",
            error="" if ok else f"run ended with status {status!r}: {metrics.get('message', '')}",
            psnr=_num(metrics.get("psnr")),
            ssim=_num(metrics.get("ssim")),
            lpips=lpips if isinstance(lpips, str) else _num(lpips),
            train_seconds=_num(metrics.get("train_seconds")),
            steps=metrics.get("steps"),
            metrics={k: v for k, v in metrics.items() if k != "per_view"},
            per_view=metrics.get("per_view", []),
        )
    except BaseException as e:  # a crashed run is recorded, never fatal for the bench
        if isinstance(e, KeyboardInterrupt):
            raise
        msg = f"{type(e).__name__}: {e}".strip().splitlines()
        result["error"] = msg[0] if msg else type(e).__name__
        (run_dir / "error.txt").write_text(traceback.format_exc())
    result["finished"] = time.time()
    earlier = earlier if result.get("resumed_from_step") else 0.0  # a fresh start owes the earlier attempts nothing
    result["wall_seconds"] = result["finished"] - started + earlier  # incl. scene loading and evaluation
    result["earlier_wall_seconds"] = earlier
    result.setdefault("versions", {})
    write_json(run_dir / RESULT_FILE, result)
    if not task.keep_checkpoint and result["status"] == "ok":
        (run_dir / CHECKPOINT_NAME).unlink(missing_ok=True)
    if task.ship_files:
        result["_files"] = _collect_files(run_dir)
    return result


def earlier_wall_seconds(run_dir: Path) -> float:
    """The wall time the earlier attempts of a run spent on what its checkpoint holds (a stopped or killed run
    resumes from there): the last attempt from its start to the checkpoint it left, plus the ones before it.
    What an attempt trained after its last checkpoint is trained again, and counted then."""
    ckpt = run_dir / CHECKPOINT_NAME
    last = read_json(run_dir / STARTED_FILE) if ckpt.is_file() else {}
    if not isinstance(last.get("started"), (int, float)):
        return 0.0
    before = last.get("earlier_wall_seconds", 0.0)
    before = float(before) if isinstance(before, (int, float)) and math.isfinite(before) else 0.0
    return before + max(0.0, ckpt.stat().st_mtime - float(last["started"]))


def _finished_twin(task: RunTask, trainer) -> dict | None:
    """The finished result of the B/L run that this run repeats step for step: a Flip run whose
    estimated plane is not confident drops its mirrors (--unconfident-plane drop) and then trains
    B/L exactly, with the same seed and the random state the estimate left untouched."""
    if not task.twin or trainer.spec.mirrors or trainer.step > 0:  # only Flip runs have a twin (runner.twin_of)
        return None
    r = read_result(Path(task.twin))
    ok = r is not None and r.get("status") == "ok" and r.get("metrics") and (Path(task.twin) / "test_renders").is_dir()
    return r if ok else None


def _reuse_twin(trainer, twin_dir: Path, twin: dict) -> dict:
    """This run's metrics without training it again: its own report (plane, confidence, coverage,
    settings) with its twin's scores, training time and test renders."""
    from flipviz.training import artifacts

    trainer.close()
    m = {
        **twin["metrics"],
        **trainer.report(),
        "per_view": twin.get("per_view", []),
        "reused_from": twin["key"],
        "run_dir": str(trainer.run_dir),
    }
    shutil.copytree(twin_dir / "test_renders", trainer.run_dir / "test_renders", dirs_exist_ok=True)
    artifacts.write_metrics(trainer.run_dir, m)
    return m


def _num(x) -> float | None:
    try:
        return None if x is None else float(x)
    except (TypeError, ValueError):
        return None


def _collect_files(run_dir: Path) -> dict[str, bytes]:
    files, total = {}, 0
    for p in sorted(run_dir.rglob("*")):
        if p.is_file() and p.suffix in SHIP_SUFFIXES and not p.name.startswith("."):
            b = p.read_bytes()
            if total + len(b) > SHIP_MAX_BYTES:
                break
            files[str(p.relative_to(run_dir))] = b
            total += len(b)
    return files


def died_result(task: RunTask, error: str = "worker process died (killed or out of memory)") -> dict:
    """The result of a run whose process died under it, written to its folder; `died`: the bench's next
    start resumes it from its last checkpoint (a run that failed on its own starts over)."""
    res = {
        "key": task.key,
        "run_id": uuid.uuid4().hex,
        **task.labels,
        "status": "failed",
        "error": error,
        "died": True,
        "psnr": None,
        "ssim": None,
        "lpips": None,
        "train_seconds": None,
        "steps": None,
        "started": None,
        "finished": time.time(),
        "train_config": task.train,
        "versions": {},
    }
    write_json(Path(task.run_dir) / RESULT_FILE, res)
    return res
