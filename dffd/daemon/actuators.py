"""The action executor's asyncio half: the scheduler's actions run on the camera's two sockets.

One worker per VISCA socket — focus and pan/tilt — each with one action in flight, so focus
moves and pan/tilt commands run concurrently. A worker translates the action with
:func:`dffd.actuation.request_for` (the translation the bench uses too), sends it over the
link, and reports the outcome with :func:`dffd.actuation.report_done` / ``report_failed``.
Recovery is the scheduler's: a failed or timed-out action is reported, not retried here (the
scheduler re-inquires the focus and re-anchors its pan/tilt model).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from dffd.actuation import (
    ActionRequest,
    completion_timeout_s,
    is_focus_action,
    report_done,
    report_failed,
    request_for,
)
from drivers.visca import codec_requests
from drivers.visca.errors import ViscaError

if TYPE_CHECKING:
    from dffd.scheduler import Action, Scheduler
    from drivers.visca.camera import Camera

_LOGGER = logging.getLogger(__name__)

# Per worker; the scheduler keeps at most one action in flight per socket, so 4 is slack.
ACTION_QUEUE_MAX = 4

__all__ = ["ACTION_QUEUE_MAX", "Actuators"]


class Actuators:
    """Runs scheduler actions on ``camera`` and reports their outcomes to ``scheduler``."""

    def __init__(
        self,
        camera: Camera,
        scheduler: Scheduler,
        on_outcome: Callable[[], object],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.camera = camera
        self.scheduler = scheduler
        self._on_outcome = on_outcome  # wakes the scheduler task
        self._clock = clock
        self._focus: asyncio.Queue[Action] = asyncio.Queue(ACTION_QUEUE_MAX)
        self._pan_tilt: asyncio.Queue[Action] = asyncio.Queue(ACTION_QUEUE_MAX)
        self.focus_failures = 0  # consecutive failed focus actions
        self.dropped = 0

    def dispatch(self, action: Action) -> None:
        """Queue ``action`` on its socket's worker (never blocks; a full queue drops it)."""
        queue = self._focus if is_focus_action(action) else self._pan_tilt
        if queue.full():  # cannot happen with one action in flight; never block the scheduler
            self.dropped += 1
            _LOGGER.warning("action queue full; dropping %r", action)
            return
        queue.put_nowait(action)

    async def run_focus(self) -> None:
        """The focus socket's worker (runs until cancelled)."""
        while True:
            action = await self._focus.get()
            ok = await self._execute(action)
            if ok and self.focus_failures:
                _LOGGER.info("focus commands work again after %d failure(s)", self.focus_failures)
                self.focus_failures = 0
            elif not ok:
                self.focus_failures += 1
            self._on_outcome()

    async def run_pan_tilt(self) -> None:
        """The pan/tilt socket's worker (runs until cancelled)."""
        while True:
            action = await self._pan_tilt.get()
            await self._execute(action)
            self._on_outcome()

    async def _execute(self, action: Action) -> bool:
        profile = self.camera.profile
        try:
            request = request_for(action, profile)
            answer = await self._send(request)
        except (ViscaError, TimeoutError, ValueError) as exc:
            if is_focus_action(action):
                # First failure of a run of failures at WARNING, the repeats at DEBUG.
                level = logging.DEBUG if self.focus_failures else logging.WARNING
                _LOGGER.log(level, "focus action %r failed: %s", action, exc)
            else:
                _LOGGER.debug("pan/tilt action %r failed: %s", action, exc)
            report_failed(self.scheduler, action, self._clock())
            return False
        report_done(self.scheduler, action, self._clock(), answer, profile)
        return True

    async def _send(self, request: ActionRequest) -> object:
        camera = self.camera
        if isinstance(
            request, codec_requests.FocusPositionInquiry | codec_requests.PanTiltPositionInquiry
        ):
            return await camera.link.inquire(camera.address, request)
        timeout = completion_timeout_s(request, camera.profile, camera.move_timeout_margin_s)
        await camera.link.command(camera.address, request, completion_timeout=timeout)
        return None
