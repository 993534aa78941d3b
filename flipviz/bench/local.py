"""Run bench tasks in worker processes on this machine, surviving a worker that dies."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from flipviz.bench.results import RESULT_FILE, STARTED_FILE, read_json
from flipviz.bench.task import RunTask, died_result, execute_run
from flipviz.errors import Interrupted

_SLOT = 0
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_RUNNING = False  # a run is under way in this worker
_STOPPING = False  # this worker was told to stop: no further run starts in it
_CTRL_C = False  # Ctrl-C reached the process group: no further run starts in this worker
STOP_GRACE_S = 30.0  # after an interrupt, how long a worker may take to save its checkpoint before it is killed


def _stop_training(signum: int, frame) -> None:
    """SIGTERM or SIGHUP in a worker: its run stops gracefully (checkpoint kept, resumable), once.

    The handler never exits the process: an idle worker is blocked in the pool's call queue
    holding its lock, and exiting there would block the other workers forever. An idle worker
    ends when the pool sends it its sentinel, or is killed after STOP_GRACE_S.
    """
    global _STOPPING
    first = not _STOPPING
    _STOPPING = True
    if _RUNNING and first:
        raise KeyboardInterrupt


def _ctrl_c(signum: int, frame) -> None:
    """Ctrl-C in a terminal reaches every worker at once with the bench. The run under way goes on until
    the bench relays SIGTERM (so it saves its checkpoint), but no queued run starts meanwhile: a worker
    that finished its run in that moment had started the next one (seen on a busy CI machine)."""
    global _CTRL_C
    _CTRL_C = True


def _init_worker(threads: int, slots) -> None:
    """Pool initializer: thread share, progress row, and exit when the bench process dies.

    On Ctrl-C (the terminal sends it to the whole process group; the bench relays it as SIGTERM) a
    worker only starts no further run; it stops its run on SIGTERM or SIGHUP, whoever sends them.
    """
    global _SLOT
    import torch

    signal.signal(signal.SIGINT, _ctrl_c)
    signal.signal(signal.SIGTERM, _stop_training)
    signal.signal(signal.SIGHUP, _stop_training)
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
    interrupted = {"key": task.key, "status": "interrupted", "error": "interrupted before it started"}
    if _STOPPING or _CTRL_C:  # a task the pool had already queued to this worker (cancel() cannot reach it)
        return interrupted
    task.slot = _SLOT
    _RUNNING = True
    try:
        return execute_run(task)
    except KeyboardInterrupt:  # the signal landed before the training loop (e.g. while the scene loaded)
        return interrupted | {"error": "interrupted while it started"}
    finally:
        _RUNNING = False


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Stop every worker within STOP_GRACE_S: SIGTERM (each run saves its checkpoint), the pool's
    sentinels for idle ones, then SIGKILL for any still alive. Further stop signals are ignored
    meanwhile, so a second Ctrl-C or a group signal cannot cut the cleanup short."""
    main = threading.current_thread() is threading.main_thread()
    before = {s: signal.signal(s, signal.SIG_IGN) for s in _STOP_SIGNALS} if main else {}
    try:
        procs = [p for p in list(getattr(pool, "_processes", {}).values()) if p.is_alive()]  # no public list
        for proc in procs:
            os.kill(proc.pid, signal.SIGTERM)
        pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + STOP_GRACE_S
        for proc in procs:
            proc.join(max(0.0, deadline - time.monotonic()))
        for proc in procs:
            if proc.is_alive():
                proc.kill()
                proc.join()
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


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
        reaper = getattr(pool, "_executor_manager_thread", None)  # it reaps the workers when the pool breaks
        tasks_this_round = list(todo)
        broken: list[RunTask] = []
        workers_seen: dict = {}  # pid -> process, taken when the pool breaks (shutdown forgets them)
        try:
            pending = set(futures)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    try:
                        res = f.result()
                    except BrokenProcessPool:
                        workers_seen = workers_seen or dict(getattr(pool, "_processes", None) or {})  # no public list
                        broken.append(futures[f])
                        continue
                    on_result(res)
                    if res.get("status") == "interrupted":  # a worker was stopped on its own: the bench stops
                        raise Interrupted(signal.SIGTERM)
        except KeyboardInterrupt:  # stop the runs under way (they keep their checkpoints), start no more
            _stop_workers(pool)
            raise
        finally:
            pool.shutdown(wait=not broken, cancel_futures=True)
        if workers_seen and reaper is not None:  # the pool stopped the others: each saves its checkpoint first,
            reaper.join(STOP_GRACE_S)  # and this thread of the pool's waits for (reaps) each worker
        for proc in workers_seen.values():  # one that did not stop in time is killed
            if proc.is_alive():
                proc.kill()
                proc.join()
        if reaper is not None:  # a worker's exit code is known once the pool's thread is done: asked earlier, it
            reaper.join(STOP_GRACE_S)  # can read None, a stopped run counted as killed (seen on a busy CI machine)
        todo = []
        for t in broken:
            res = read_json(Path(t.run_dir) / RESULT_FILE)
            started = read_json(Path(t.run_dir) / STARTED_FILE)
            if res.get("finished", 0) >= round_start:  # finished just before the pool broke
                on_result(res)
            elif started.get("started", 0) >= round_start and _died(workers_seen.get(started.get("pid"))):
                on_result(died_result(t))  # its own process died under it (killed, out of memory)
            else:
                todo.append(t)  # never started, or stopped because another worker died: go on in a fresh pool
        if todo and len(todo) == len(tasks_this_round):
            raise RuntimeError("bench worker processes die before starting any run")


def _died(proc) -> bool:
    """A worker ended by a signal it did not handle (SIGKILL, the OOM killer, a crash): its run died with it.
    A worker the broken pool stopped with SIGTERM stopped its run gracefully, keeping its checkpoint
    (_stop_training), and exited with a code of its own. Unknown (no such worker): died."""
    return proc is None or proc.exitcode is None or proc.exitcode < 0
