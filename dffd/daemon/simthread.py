"""The simulated camera's VISCA server on an event loop of its own, in a thread of its own.

A real camera is another device; the simulator stands in for it inside the daemon's process. Its
VISCA server (the pty, UDP or TCP one, with the device's paced replies and timers) ran on the
daemon's event loop, where it took ~10 % of the loop's CPU and delayed the service's own
callbacks. :class:`SimThread` enters the server's async context manager on a new event loop in
a thread named ``sim-camera`` and leaves it there on exit, so the service's loop carries only the
service (and the bench can tell the simulator's CPU from the service's by the thread's name).
The server and the renderer share the simulated camera's state under its lock, as before.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import threading
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from types import TracebackType
from typing import Generic, TypeVar

__all__ = ["SIM_THREAD_NAME", "SIM_THREAD_START_TIMEOUT_S", "SimThread"]

_T = TypeVar("_T")

SIM_THREAD_NAME = "sim-camera"
# Opening the pty or a loopback socket and powering the simulated camera up takes milliseconds;
# 10 s covers a loaded 2-core machine.
SIM_THREAD_START_TIMEOUT_S = 10.0
# Leaving the server's context (closing the pty or sockets) takes milliseconds as well.
SIM_THREAD_STOP_TIMEOUT_S = 5.0


class SimThread(Generic[_T]):
    """``async with SimThread(factory) as server``: ``factory()``'s context, entered in a thread."""

    def __init__(
        self,
        factory: Callable[[], AbstractAsyncContextManager[_T]],
        name: str = SIM_THREAD_NAME,
    ) -> None:
        self._factory = factory
        self._ready: concurrent.futures.Future[_T] = concurrent.futures.Future()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)

    async def __aenter__(self) -> _T:
        """Start the thread; the entered server once it is serving (its errors re-raised)."""
        self._thread.start()
        async with asyncio.timeout(SIM_THREAD_START_TIMEOUT_S):
            return await asyncio.wrap_future(self._ready)

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Leave the server's context in its thread and join the thread."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # its loop has ended already
                loop.call_soon_threadsafe(stop.set)
        await asyncio.to_thread(self._thread.join, SIM_THREAD_STOP_TIMEOUT_S)

    def _main(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # noqa: BLE001 - handed to __aenter__ if it still waits
            if not self._ready.done():
                self._ready.set_exception(exc)

    async def _serve(self) -> None:
        self._stop = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        async with self._factory() as server:
            self._ready.set_result(server)
            await self._stop.wait()
