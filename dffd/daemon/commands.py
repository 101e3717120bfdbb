"""Commands from MQTT (and the web dashboard) on the running daemon: acquire, release, known
size, home, burst policy. The core is changed only by the estimator thread, between frames."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from dffd.mqtt import models
from dffd.mqtt.commands import CommandRejected
from drivers.visca.errors import ViscaError

if TYPE_CHECKING:
    from dffd.config import DffdConfig
    from dffd.core.pipeline import Pipeline
    from dffd.daemon.estimator import EstimatorThread
    from dffd.scheduler import Scheduler
    from drivers.visca.camera import Camera

_LOGGER = logging.getLogger(__name__)

# Core commands wait at most this long for the estimator thread to apply them (it is between
# two frames within ~1 ms unless it is behind; 2 s stays under the command path's own 5 s bound,
# dffd.mqtt.commands.COMMAND_TIMEOUT_S).
CORE_COMMAND_TIMEOUT_S = 2.0

__all__ = ["CORE_COMMAND_TIMEOUT_S", "Commands", "apply_to_core"]


class Commands:
    """Executes validated commands on the scheduler, the core and the camera."""

    def __init__(
        self,
        settings: DffdConfig,
        scheduler: Scheduler,
        estimator: EstimatorThread,
        *,
        camera: Callable[[], Camera | None],
        wake: Callable[[], object],
        acquired: Callable[[tuple[int, int, int, int] | None], object],
        released: Callable[[], object],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.scheduler = scheduler
        self.estimator = estimator
        self._camera = camera  # None until the camera is initialised
        self._wake = wake  # the scheduler task re-plans after a command
        self._acquired = acquired  # the shell's view: the core searches (in this ROI)
        self._released = released  # the shell's view: idle, nothing stale published
        self._clock = clock

    async def execute(self, command: models.Command) -> dict[str, Any] | None:
        """Run ``command``; its reply's ``result`` (CommandRejected: refused, with advice)."""
        sched = self.scheduler
        if isinstance(command, models.Acquire) and command.roi is None:
            await apply_to_core(self.estimator, lambda p: p.acquire_auto())
            sched.arm_search(self._clock())
            self._wake()
            self._acquired(None)
            after = sched.config.search_after_s
            _LOGGER.info(
                "acquire: searching the whole frame for the target (automatic detection)%s",
                ""
                if after is None
                else f"; pan/tilt sweeps its range if none is seen in {after:g} s",
            )
            return {"roi": None}
        if isinstance(command, models.Acquire):
            assert command.roi is not None
            x, y, w, h = command.roi
            fw, fh = sched.config.frame_size
            if x + w > fw or y + h > fh:
                raise CommandRejected(
                    f"roi {list(command.roi)} extends beyond the {fw}x{fh} frame; "
                    "give [x, y, w, h] inside the image"
                )
            await apply_to_core(self.estimator, lambda p: p.acquire_roi(x, y, w, h))
            sched.disarm_search()  # the operator pointed at this view: no sweep until seen
            self._wake()
            self._acquired((x, y, w, h))
            _LOGGER.info("acquire: target inside roi [%d, %d, %d, %d]", x, y, w, h)
            return {"roi": [x, y, w, h]}
        if isinstance(command, models.Release):
            await apply_to_core(self.estimator, lambda p: p.release())
            sched.cancel_bursts()
            sched.stop_pan_tilt()
            self._wake()
            self._released()
            _LOGGER.info("released by command: idle, no depths published until 'acquire'")
            return None
        if isinstance(command, models.SetKnownSize):
            size = command.size_m
            await apply_to_core(self.estimator, lambda p: p.set_known_size(size))
            return {"size_m": size}
        if isinstance(command, models.Home):
            camera = self._camera()
            if camera is None:
                raise CommandRejected("camera not initialised yet; retry")
            armed = sched.search_armed
            sched.stop_pan_tilt()
            self._wake()
            try:
                await camera.home()
            except ViscaError as exc:
                raise CommandRejected(f"home failed: {exc}") from exc
            finally:
                sched.on_pan_tilt_failed(self._clock())  # re-anchor the model by inquiry
                if armed:  # automatic acquisition goes on from home (its timer restarts)
                    sched.arm_search(self._clock())
                self._wake()
            return None
        if isinstance(command, models.SetBurstPolicy):
            cfg = sched.config
            every = command.every_n_frames or cfg.burst_every_frames
            sigma = None
            if command.policy == "sigma":
                sigma = command.sigma_threshold_m or self.settings.scheduler.sigma_threshold_m
            sched.set_policy(every, sigma)
            self._wake()
            return {"policy": command.policy, "every_n_frames": every, "sigma_threshold_m": sigma}
        raise CommandRejected(f"unsupported command {command!r}")


async def apply_to_core(estimator: EstimatorThread, command: Callable[[Pipeline], object]) -> None:
    """Run ``command`` on the core in the estimator thread; CommandRejected if it fails or the
    thread does not get to it within :data:`CORE_COMMAND_TIMEOUT_S`."""

    def wrapped(pipeline: Pipeline) -> dict[str, Any] | None:
        command(pipeline)
        return None

    future = estimator.call(wrapped)
    try:
        async with asyncio.timeout(CORE_COMMAND_TIMEOUT_S):
            await asyncio.wrap_future(future)
    except ValueError as exc:
        raise CommandRejected(str(exc)) from exc
    except TimeoutError as exc:
        raise CommandRejected(
            f"the estimator did not apply the command within {CORE_COMMAND_TIMEOUT_S:.0f} s "
            "(it is behind on frames); retry"
        ) from exc
