"""Run bench tasks in worker processes on this machine, surviving a worker that dies."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from flipviz.bench.results import RESULT_FILE, STARTED_FILE
from flipviz.bench.task import RunTask, died_result, execute_run

_SLOT = 0


_RUNNING = False  # a run is under way in this worker
_STOPPING = False  # the bench was interrupted: no further run starts in this worker


def _stop_training(signum: int, frame) -> None:
    global _STOPPING
    _STOPPING = True
    if not _RUNNING:  # idle: nothing to save
        os._exit(0)
    raise KeyboardInterrupt  # the run in this worker stops gracefully: checkpoint kept, resumable


def _init_worker(threads: int, slots) -> None:
    """Pool initializer: thread share, progress row, and exit when the bench process dies.

    A worker ignores Ctrl-C (the terminal sends it to the whole process group) and stops its run on
    SIGTERM, which the bench sends to every worker when it is interrupted.
    """
    global _SLOT
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop_training)
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
    global _RUNNING
    if _STOPPING:  # a task the pool had already queued to this worker (cancel() cannot reach it)
        return {"key": task.key, "status": "interrupted", "error": "interrupted before it started"}
    task.slot = _SLOT
    _RUNNING = True
    try:
        return execute_run(task)
    finally:
        _RUNNING = False


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
        except KeyboardInterrupt:  # stop the runs under way (they keep their checkpoints), start no more
            for f in futures:
                f.cancel()
            for proc in list(getattr(pool, "_processes", {}).values()):  # the pool has no public list of its workers
                if proc.is_alive():
                    os.kill(proc.pid, signal.SIGTERM)
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        finally:
            pool.shutdown(wait=not broken, cancel_futures=True)
        todo = []
        for t in broken:
            res = _read_json(Path(t.run_dir) / RESULT_FILE)
            if res.get("finished", 0) >= round_start:  # finished just before the pool broke
                on_result(res)
            elif _read_json(Path(t.run_dir) / STARTED_FILE).get("started", 0) >= round_start:
                on_result(died_result(t))  # the process died under it
            else:
                todo.append(t)  # never started: try again in a fresh pool
        if todo and len(todo) == len(tasks_this_round):
            raise RuntimeError("bench worker processes die before starting any run")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
