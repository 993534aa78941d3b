"""One thread writes the browser's state: viser's event loop.

viser wakes its sender with `asyncio.Event.set()` from whichever thread queues a message, and an
asyncio Event is not thread-safe: `set()` walks the event's waiters while the loop thread may be
adding one. An update from another thread therefore now and then raised "RuntimeError: deque
mutated during iteration" (seen in the app's UI thread while dropdowns were used). Work that
updates the GUI in bulk from flipviz's own threads runs through `on_gui_thread`, on the loop thread,
one piece after another.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from typing import Callable, TypeVar

import viser

T = TypeVar("T")


def on_gui_thread(server: viser.ViserServer, fn: Callable[[], T], timeout: float | None = None) -> T:
    """Run `fn` on viser's event loop thread and return its result (at once when already there)."""
    loop = server.get_event_loop()
    if _current_loop() is loop:
        return fn()
    done: concurrent.futures.Future[T] = concurrent.futures.Future()

    def run() -> None:
        try:
            done.set_result(fn())
        except BaseException as e:  # noqa: BLE001 - handed back to the caller's thread
            done.set_exception(e)

    loop.call_soon_threadsafe(run)
    return done.result(timeout)


def _current_loop() -> asyncio.AbstractEventLoop | None:
    """The event loop this thread is running (None outside one)."""
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None
