"""Files that are either complete or absent: every write in flipviz goes through `atomic_path`."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from flipviz.errors import UserError


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a unique temporary path beside `path`; on success rename it over `path`, else remove it.

    The temporary name keeps the suffix (writers such as cv2 pick the format from it) and is unique
    per process and call, so concurrent writers never share one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb+") as f:  # flush to disk before the rename makes it visible
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def cannot_write(path: Path | str, what: str) -> Iterator[None]:
    """An OSError inside the block (a full disk, a read-only folder) is one UserError line naming
    `what` and `path`; atomic_path inside has already kept any earlier file."""
    try:
        yield
    except OSError as e:
        left = free_bytes(path)
        free = f" ({left / 1e6:.0f} MB free there)" if e.errno == errno.ENOSPC or left < LOW_SPACE else ""
        raise UserError(f"cannot write {what} {path}: {e.strerror or e}{free}") from None


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)  # Ctrl-C, kill, a closed terminal: stop gracefully
LOW_SPACE = 64e6  # bytes: a write error with less free than this names the free space


def free_bytes(path: Path | str) -> int:
    """Free space on the disk that holds `path` (or its nearest existing parent)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


def need_space(path: Path | str, nbytes: float, what: str) -> None:
    """An OSError (ENOSPC) naming `what` when the disk of `path` has less than `nbytes` free: a real
    full disk fails inside writers (torch's zip writer, Rerun's file sink) in ways that are no
    OSError and leave no readable file, so writers ask first."""
    free = free_bytes(path)
    if free < nbytes:
        raise OSError(
            errno.ENOSPC, f"{what} needs about {nbytes / 1e6:.0f} MB, {free / 1e6:.0f} MB are free on that disk"
        )


TEMP_NAME = re.compile(r"^\..+\.\d+-[0-9a-f]{8}\.tmp")  # atomic_path's temporary names


def remove_leftover_temps(folder: Path) -> int:
    """Delete the temporary files that killed writes left in `folder` (a 50 MB checkpoint each);
    call it holding the folder's lock, so that no write of another process is under way there."""
    removed = 0
    for p in Path(folder).iterdir() if Path(folder).is_dir() else ():
        if p.is_file() and TEMP_NAME.match(p.name):
            p.unlink(missing_ok=True)
            removed += 1
    return removed


def write_text(path: Path | str, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: Path | str, data: Any) -> Path:
    """JSON with numpy arrays / scalars and paths turned into plain values."""
    return write_text(path, json.dumps(data, indent=2, default=_plain))


def _plain(o: Any) -> Any:
    if hasattr(o, "tolist"):  # numpy / torch arrays and scalars
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


class FolderLock:
    """An exclusive lock on a folder (`.flipviz.lock` inside it), held until `release()` or exit.

    A second process asking for the same folder gets a one-line UserError naming the holder, so
    two runs never write into one run folder.
    """

    NAME = ".flipviz.lock"

    def __init__(self, folder: Path | str, what: str = "run folder") -> None:
        self.path = Path(folder) / self.NAME
        self._made_folder = not self.path.parent.exists()
        try:  # creating the folder and its lock file is the first write: say plainly when it fails
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "a+")
        except OSError as e:
            raise UserError(f"cannot write the {what} {self.path.parent}: {e.strerror or e}") from None
        holder = _flock_or_holder(self._f)
        if holder is not None:
            self._f.close()
            raise UserError(f"{what} {self.path.parent} is in use by {holder}; choose another --out")
        try:  # who holds it, for a second process's refusal; a full disk refuses here, in one line
            self._f.seek(0)
            self._f.truncate()
            self._f.write(f"flipviz pid {os.getpid()}")
            self._f.flush()
        except OSError as e:
            self.abandon()
            raise UserError(f"cannot write the {what} {self.path.parent}: {e.strerror or e}") from None

    @classmethod
    def holder(cls, folder: Path | str) -> str | None:
        """Who holds `folder`'s lock ("flipviz pid N"), or None when no live process does."""
        try:
            with open(Path(folder) / cls.NAME, "r+") as f:
                return _flock_or_holder(f)  # taken for a moment only: closing the file drops it
        except OSError:  # no lock file (or unreadable): not a run folder in use
            return None

    def release(self) -> None:
        if not self._f.closed:
            try:
                self._f.close()  # closing drops the flock
            except OSError:  # its last write could not be flushed (a full disk): the file is closed all the same
                pass

    def abandon(self) -> None:
        """Release the folder, and remove it again when this lock created it and nothing else was
        written there: a run refused during its setup leaves no empty run folder behind."""
        self.release()
        if self._made_folder and [p.name for p in self.path.parent.iterdir()] == [self.NAME]:
            self.path.unlink(missing_ok=True)
            self.path.parent.rmdir()


def _flock_or_holder(f) -> str | None:
    """Take an exclusive lock on the open file `f`: None when it is ours, else who holds it."""
    import fcntl

    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return None
    except OSError:
        f.seek(0)
        return f.read().strip() or "another process"


def next_free(path: Path | str) -> Path:
    """`path` when nothing is there yet, else the first free `stem.N.suffix` beside it: a write that
    must never replace an earlier file (a recording of another run, a resumed run's first one)."""
    path = Path(path)
    if not path.exists():
        return path
    return next(p for n in range(1, 1_000_000) if not (p := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists())


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Ctrl-C, SIGTERM and SIGHUP wait until the block ends, so that a file being written is never
    cut in half by an interrupt: their handlers are swapped for ones that only take note, and the
    first signal noted is handled once the block is done. Main thread only (elsewhere a no-op:
    Python delivers signals to the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    noted: list[int] = []
    old = {s: signal.signal(s, lambda signum, frame: noted.append(signum)) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if noted:
            handler = old[noted[0]]
            if callable(handler):  # Python's own (KeyboardInterrupt) or flipviz's CLI handler
                handler(noted[0], None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(noted[0])


def inside_folder(root: Path, relative: str, listed_in: str) -> Path:
    """`root / relative` when it stays inside `root` (checked on the names, so links inside the folder
    still work), else a one-line UserError: a dataset file never makes flipviz read outside its folder."""
    p = Path(os.path.normpath(Path(root) / relative))
    if Path(relative).is_absolute() or not p.is_relative_to(os.path.normpath(root)):
        raise UserError(f"{listed_in} names {relative!r}, outside its folder {root}; flipviz reads only inside it")
    return p


def inside_roots(path: Path | str, roots: list[Path], what: str) -> Path:
    """`path` resolved (links followed) when it lies in one of `roots`, else a one-line UserError.

    For folders a browser names (the app's Compare and Restart): a browser may open only what the
    person who started the app named on its command line, never `/etc` or `~/.ssh`.
    """
    try:
        p = Path(path).expanduser().resolve()
    except (OSError, RuntimeError, ValueError) as e:  # a link loop, a NUL byte
        raise UserError(f"{what} {str(path)!r} is not a usable path ({type(e).__name__})") from None
    resolved = [Path(r).expanduser().resolve() for r in roots]
    if not any(p == r or p.is_relative_to(r) for r in resolved):
        allowed = ", ".join(str(r) for r in sorted(set(resolved))) or "none"
        raise UserError(
            f"{what} {str(path)!r} is outside the folders this app may open ({allowed}); "
            "start the app with --browse-root FOLDER to allow another"
        )
    return p
