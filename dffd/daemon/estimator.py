"""The estimator thread: the core step in one dedicated thread behind one bounded queue.

Frames come in through a drop-oldest queue (capture never blocks; drops are counted); each is
processed with :meth:`dffd.step.CoreStep.step` and the result handed to ``deliver`` (the
daemon passes it to the event loop with ``call_soon_threadsafe``). Commands that change the
core (acquire, release, known size) run in this thread between frames, so the core is never
touched concurrently.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from dffd.core.pipeline import Pipeline
from dffd.core.types import FrameTag
from dffd.mqtt.commands import CommandRejected
from dffd.step import CoreStep, StepResult
from drivers.frames import Frame

_LOGGER = logging.getLogger(__name__)

# Bounded queues (no unbounded queue anywhere).
FRAME_QUEUE_MAX = 4  # estimator input: a few frames of slack at 30 fps, then drop the oldest
COMMAND_QUEUE_MAX = 16  # core commands waiting for the estimator thread
# The thread waits for frames in slices so it notices a stop request.
ESTIMATOR_POLL_S = 0.2
ESTIMATOR_JOIN_TIMEOUT_S = 2.0

__all__ = ["CoreCommand", "EstimatorResult", "EstimatorThread"]


@dataclass(frozen=True, slots=True)
class EstimatorResult:
    """One processed frame, handed back to the event loop."""

    step: StepResult
    cpu_s: float  # estimator thread CPU time spent on the frame
    frame: Frame  # the processed frame (the dashboard draws on the newest one)

    @property
    def frame_index(self) -> int:
        """Index of the processed frame."""
        return self.step.frame_index


CoreCommand = Callable[[Pipeline], dict[str, Any] | None]


class EstimatorThread:
    """The core in one dedicated thread behind one bounded drop-oldest queue."""

    def __init__(
        self,
        core: CoreStep,
        deliver: Callable[[EstimatorResult], object],
        queue_max: int = FRAME_QUEUE_MAX,
    ) -> None:
        self.core = core
        self._deliver = deliver
        self._frames: deque[_Work] = deque(maxlen=queue_max)
        self._commands: deque[tuple[CoreCommand, Future[dict[str, Any] | None]]] = deque(
            maxlen=COMMAND_QUEUE_MAX
        )
        self._cond = threading.Condition()
        self._stop = False
        self.dropped = 0
        self.processed = 0
        self._thread = threading.Thread(target=self._run, name="dffd-estimator", daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def submit(self, frame: Frame, tag: FrameTag) -> None:
        """Queue a frame (never blocks; drops the oldest queued frame when full)."""
        with self._cond:
            if len(self._frames) == self._frames.maxlen:
                self.dropped += 1
            self._frames.append(_Work(frame, tag))
            self._cond.notify()

    def call(self, command: CoreCommand) -> Future[dict[str, Any] | None]:
        """Run ``command(pipeline)`` in the estimator thread before the next frame."""
        future: Future[dict[str, Any] | None] = Future()
        with self._cond:
            if len(self._commands) == self._commands.maxlen:
                future.set_exception(CommandRejected("too many pending commands; retry"))
                return future
            self._commands.append((command, future))
            self._cond.notify()
        return future

    def stop(self, timeout_s: float = ESTIMATOR_JOIN_TIMEOUT_S) -> bool:
        """Ask the thread to finish and join it; True if it did in time."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not (self._stop or self._frames or self._commands):
                    self._cond.wait(ESTIMATOR_POLL_S)
                if self._stop:
                    return
                commands = list(self._commands)
                self._commands.clear()
                work = self._frames.popleft() if self._frames else None
            for command, future in commands:
                try:
                    future.set_result(command(self.core.pipeline))
                except Exception as exc:  # noqa: BLE001 - a bad command is answered, never fatal
                    future.set_exception(exc)
            if work is not None:
                try:
                    self._deliver(self._process(work))
                except Exception:  # the core must not kill the service on one bad frame
                    _LOGGER.exception("estimator failed on frame %d", work.frame.index)

    def _process(self, work: _Work) -> EstimatorResult:
        c0 = time.thread_time()
        step = self.core.step(work.frame, work.tag)
        self.processed += 1
        return EstimatorResult(step, time.thread_time() - c0, work.frame)


@dataclass(frozen=True, slots=True)
class _Work:
    frame: Frame
    tag: FrameTag
