"""Browser updates from any thread: viser's message buffer made thread-safe, and bulk work on its loop.

viser (1.1.1, `infra/_async_message_buffer.py: push`) queues each message under a lock and then
calls `message_event.set()` from whichever thread queued it. An asyncio Event is not thread-safe:
`set()` walks the event's waiters while the loop thread may be adding one, so an update from
another thread now and then raised "RuntimeError: deque mutated during iteration" (seen in the
app while dropdowns were used). flipviz writes to the GUI from its render worker, its UI tick,
viser's callback threads and the estimate's thread, so the fix is at that one point:

- `thread_safe_pushes()` gives every message buffer a `LoopEvent`, whose `set()` off the loop thread
  only asks the loop to wake its waiters (`call_soon_threadsafe`); on the loop it wakes them as before.
  push() itself already wakes the loop the same way after its direct set(), so nothing is lost.
- `on_gui_thread(server, fn)` runs bulk work (the UI tick) on the loop thread, one piece after another.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
from collections.abc import Callable
from typing import TypeVar

import viser
from viser.infra._async_message_buffer import AsyncMessageBuffer

T = TypeVar("T")


class LoopEvent(asyncio.Event):
    """An asyncio.Event of `loop` that any thread may set(): its waiters are only touched on the loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self._loop = loop

    def set(self) -> None:
        if _current_loop() is self._loop:
            super().set()
            return
        try:
            self._loop.call_soon_threadsafe(super().set)
        except RuntimeError:  # the loop is closed (the server stopped): nobody waits any more
            pass


def thread_safe_pushes() -> None:
    """Give each viser message buffer created from now on a LoopEvent (idempotent; call before the server)."""
    init = AsyncMessageBuffer.__init__
    if getattr(init, "_flipviz_loop_event", False):
        return

    @functools.wraps(init)
    def with_loop_event(self: AsyncMessageBuffer, *args, **kwargs) -> None:
        init(self, *args, **kwargs)
        self.message_event = LoopEvent(self.event_loop)

    with_loop_event._flipviz_loop_event = True
    AsyncMessageBuffer.__init__ = with_loop_event


def on_gui_thread(server: viser.ViserServer, fn: Callable[[], T], timeout: float | None = None) -> T:
    """Run `fn` on viser's event loop thread and return its result (at once when already there)."""
    loop = server.get_event_loop()
    if _current_loop() is loop:
        return fn()
    done: concurrent.futures.Future[T] = concurrent.futures.Future()

    def run() -> None:
        try:
            done.set_result(fn())
        except BaseException as e:
            done.set_exception(e)

    loop.call_soon_threadsafe(run)
    return done.result(timeout)


def _current_loop() -> asyncio.AbstractEventLoop | None:
    """The event loop this thread is running (None outside one)."""
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None
