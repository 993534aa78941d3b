"""Run bench tasks on a Ray cluster; remote runs ship their small output files back."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from flipviz.bench.task import RunTask, died_result, execute_run
from flipviz.files import atomic_path


def run_ray(
    tasks: list[RunTask], address: str | None, cpus_per_run: int, gpus_per_run: float, on_result: Callable[[dict], None]
) -> None:
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


def _run_ray_tasks(
    ray, tasks: list[RunTask], cpus_per_run: int, gpus_per_run: float, env_vars: dict, on_result: Callable[[dict], None]
) -> None:
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
                res = died_result(t, "ray task failed: " + (msg[0] if msg else ""))
            _write_shipped(Path(t.run_dir), res.pop("_files", {}))
            on_result(res)


def _write_shipped(run_dir: Path, files: dict[str, bytes]) -> None:
    """Store a remote run's small outputs in this machine's run folder (same bytes if local)."""
    for rel, data in files.items():
        p = run_dir / rel
        if p.is_file() and p.stat().st_size == len(data):
            continue
        with atomic_path(p) as tmp:
            tmp.write_bytes(data)


def _flipviz_installed() -> bool:
    try:
        from importlib.metadata import version

        version("flipviz")
        return True
    except Exception:
        return False
