"""Where runs execute: worker processes on this machine, or tasks on a Ray cluster.

A task is plain data (`RunTask`); `execute_run` trains it, scores the unobserved views, writes
`<run_dir>/result.json` atomically and returns the result. Exceptions become a "failed" result
with the error, so one crash never stops the other runs.
"""

from __future__ import annotations

import json
import os
import re
import sys
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, replace
from pathlib import Path

RESULT_FILE = "result.json"
STARTED_FILE = "started.json"
CHECKPOINT_FILE = "checkpoint.pt"
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


def write_json_atomic(path: Path, data: dict) -> None:
    """Write JSON to a unique temporary file, fsync, then rename over `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=2, default=_json_default)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _json_default(o):
    if hasattr(o, "tolist"):  # numpy / torch arrays and scalars
        return o.tolist()
    return str(o)  # paths and anything else


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


def _bar_observer(task: RunTask):
    """A per-run tqdm bar (ray's tqdm inside a Ray worker, so the driver draws it)."""
    from flipviz.training.events import Observer

    in_ray = "ray" in sys.modules and _inside_ray_worker()
    if in_ray:
        from ray.experimental.tqdm_ray import tqdm as bar_cls
    else:
        from tqdm import tqdm as bar_cls

    class BarObserver(Observer):
        def __init__(self) -> None:
            self.bar = None

        def on_setup(self, event) -> None:
            kw = {"position": task.slot + 1, "leave": False, "dynamic_ncols": True, "file": sys.stderr}
            kw = {} if in_ray else kw
            self.bar = bar_cls(total=event.total_steps, desc=f"{event.scene} {_label(task)} cfg{event.config}", **kw)

        def on_step(self, event) -> None:
            if self.bar is not None:
                self.bar.update(max(0, event.step - self.bar.n))

        def on_end(self, event) -> None:
            if self.bar is not None:
                self.bar.close()
                self.bar = None

    return BarObserver()


def _label(task: RunTask) -> str:
    lab = task.labels
    if lab.get("default_flags", True):
        return lab["method"]
    return f"{lab['method']} (ba={int(lab['ba'])},u={int(lab['uncertainty'])})"


def _inside_ray_worker() -> bool:
    try:
        import ray

        return ray.is_initialized() and ray.get_runtime_context().worker.mode == ray.WORKER_MODE
    except Exception:
        return False


def _train(cfg, observers: list) -> dict:
    """One training through the trainer's public API; returns its final metrics.

    A run folder with a checkpoint but no result (the bench was killed mid-run) resumes from it.
    """
    from flipviz.training.trainer import Trainer

    ckpt = Path(cfg.out) / CHECKPOINT_FILE if cfg.out is not None else None
    trainer = None
    if ckpt is not None and ckpt.is_file() and cfg.resume is None:
        try:
            trainer = Trainer(replace(cfg, resume=ckpt))
        except Exception:  # an unreadable or foreign checkpoint: start over
            trainer = None
    if trainer is None:
        trainer = Trainer(cfg)
    for obs in observers:
        trainer.add_observer(obs)
    return trainer.run()


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
    started = time.time()
    run_id = uuid.uuid4().hex
    host = os.uname().nodename
    write_json_atomic(run_dir / STARTED_FILE, {"run_id": run_id, "started": started, "pid": os.getpid(), "host": host})
    result = {
        "key": task.key, "run_id": run_id, **task.labels, "status": "failed", "error": "",
        "psnr": None, "ssim": None, "lpips": None, "train_seconds": None, "steps": None,
        "started": started, "finished": None, "threads": task.threads, "host": host,
        "train_config": task.train,
    }  # fmt: skip
    try:
        result["versions"] = versions()
        from flipviz.training.config import TrainConfig

        kw = dict(task.train)
        for k in ("data", "out", "rrd", "resume"):
            if kw.get(k) is not None:
                kw[k] = Path(kw[k])
        cfg = TrainConfig(**kw)
        observers = [_bar_observer(task)] if task.progress else []
        metrics = _train(cfg, observers) or {}
        status = metrics.get("status", "finished")
        ok = status in ("finished", "ok")
        lpips = metrics.get("lpips")
        if status == "stopped":  # Ctrl-C: not a result; the restart resumes from the checkpoint
            return result | {"status": "interrupted", "error": "interrupted"}
        result.update(
            status="ok" if ok else "failed",
            error="" if ok else f"run ended with status {status!r}: {metrics.get('message', '')}",
            psnr=_num(metrics.get("psnr")), ssim=_num(metrics.get("ssim")),
            lpips=lpips if isinstance(lpips, str) else _num(lpips),
            train_seconds=_num(metrics.get("train_seconds")), steps=metrics.get("steps"),
            metrics={k: v for k, v in metrics.items() if k != "per_view"}, per_view=metrics.get("per_view", []),
        )  # fmt: skip
    except BaseException as e:  # a crashed run is recorded, never fatal for the bench
        if isinstance(e, KeyboardInterrupt):
            raise
        msg = f"{type(e).__name__}: {e}".strip().splitlines()
        result["error"] = msg[0] if msg else type(e).__name__
        (run_dir / "error.txt").write_text(traceback.format_exc())
    result["finished"] = time.time()
    result["wall_seconds"] = result["finished"] - started  # incl. scene loading and evaluation
    result.setdefault("versions", {})
    write_json_atomic(run_dir / RESULT_FILE, result)
    if not task.keep_checkpoint and result["status"] == "ok":
        (run_dir / CHECKPOINT_FILE).unlink(missing_ok=True)
    if task.ship_files:
        result["_files"] = _collect_files(run_dir)
    return result


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


# ------------------------------------------------------------------ local worker processes


_SLOT = 0


def _init_worker(threads: int, slots) -> None:
    """Pool initializer: thread share, progress row, and exit when the bench process dies."""
    global _SLOT
    import torch

    torch.set_num_threads(max(1, threads))
    _SLOT = slots.get()
    parent = os.getppid()

    def watchdog() -> None:  # a killed bench must not leave orphan trainings running
        while True:
            time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watchdog, daemon=True).start()


def _run_in_worker(task: RunTask) -> dict:
    task.slot = _SLOT
    return execute_run(task)


def run_local(tasks: list[RunTask], workers: int, on_result: Callable[[dict], None]) -> None:
    """Run tasks in `workers` spawned processes. If a process dies (e.g. out of memory), the runs
    it had started are recorded as failed and the rest go on in a fresh pool."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")  # workers inherit OMP_WAIT_POLICY=PASSIVE (set in flipviz/__init__.py)
    todo = list(tasks)
    while todo:
        round_start = time.time()
        n = max(1, min(workers, len(todo)))
        slots = ctx.Queue()
        for i in range(n):
            slots.put(i)
        threads = todo[0].threads
        pool = ProcessPoolExecutor(n, mp_context=ctx, initializer=_init_worker, initargs=(threads, slots))
        futures = {pool.submit(_run_in_worker, t): t for t in todo}
        tasks_this_round = list(todo)
        broken: list[RunTask] = []
        try:
            pending = set(futures)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    try:
                        on_result(f.result())
                    except BrokenProcessPool:
                        broken.append(futures[f])
        finally:
            pool.shutdown(wait=not broken, cancel_futures=True)
        todo = []
        for t in broken:
            res = _read_json(Path(t.run_dir) / RESULT_FILE)
            if res.get("finished", 0) >= round_start:  # finished just before the pool broke
                on_result(res)
            elif _read_json(Path(t.run_dir) / STARTED_FILE).get("started", 0) >= round_start:
                on_result(_died_result(t))  # the process died under it
            else:
                todo.append(t)  # never started: try again in a fresh pool
        if todo and len(todo) == len(tasks_this_round):
            raise RuntimeError("bench worker processes die before starting any run")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _died_result(task: RunTask, error: str = "worker process died (killed or out of memory)") -> dict:
    res = {"key": task.key, "run_id": uuid.uuid4().hex, **task.labels, "status": "failed", "error": error,
           "psnr": None, "ssim": None, "lpips": None, "train_seconds": None, "steps": None, "started": None,
           "finished": time.time(), "train_config": task.train, "versions": {}}  # fmt: skip
    write_json_atomic(Path(task.run_dir) / RESULT_FILE, res)
    return res


# ------------------------------------------------------------------------------------- Ray


def run_ray(tasks: list[RunTask], address: str | None, cpus_per_run: int, gpus_per_run: float,
            on_result: Callable[[dict], None]) -> None:  # fmt: skip
    """Spread tasks over a Ray cluster (`address`, or a local Ray when None / 'local')."""
    try:
        import ray
    except ImportError:
        raise SystemExit("flipviz: error: the Ray executor needs ray: pip install 'flipviz[cluster]'") from None
    env_vars = {k: v for k, v in os.environ.items() if k.startswith(("FLIPVIZ_", "MALLOC_"))}
    env_vars.setdefault("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    if not _flipviz_installed():  # a source checkout: let the workers import it from here
        root = str(Path(__file__).resolve().parents[2])
        env_vars["PYTHONPATH"] = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=None if address in (None, "local") else address, include_dashboard=False)
    try:
        _run_ray_tasks(ray, tasks, cpus_per_run, gpus_per_run, env_vars, on_result)
    finally:
        if started_here:
            ray.shutdown()


def _run_ray_tasks(ray, tasks: list[RunTask], cpus_per_run: int, gpus_per_run: float, env_vars: dict,
                   on_result: Callable[[dict], None]) -> None:  # fmt: skip
    remote = ray.remote(execute_run).options(
        num_cpus=cpus_per_run, num_gpus=gpus_per_run, max_retries=0, runtime_env={"env_vars": env_vars}
    )
    refs = {remote.remote(asdict(t) | {"ship_files": True}): t for t in tasks}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        for ref in done:
            t = refs[ref]
            try:
                res = ray.get(ref)
            except Exception as e:  # the worker died or ray failed the task
                msg = f"{type(e).__name__}: {e}".strip().splitlines()
                res = _died_result(t, "ray task failed: " + (msg[0] if msg else ""))
            _write_shipped(Path(t.run_dir), res.pop("_files", {}))
            on_result(res)


def _write_shipped(run_dir: Path, files: dict[str, bytes]) -> None:
    """Store a remote run's small outputs in this machine's run folder (same bytes if local)."""
    for rel, data in files.items():
        p = run_dir / rel
        if p.is_file() and p.stat().st_size == len(data):
            continue
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{uuid.uuid4().hex[:8]}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, p)


def _flipviz_installed() -> bool:
    try:
        from importlib.metadata import version

        version("flipviz")
        return True
    except Exception:
        return False
