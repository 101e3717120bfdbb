"""The daemon's side of the web dashboard: what it shows, its metrics, the server's lifetime.

The daemon calls :meth:`Dashboard.on_result` for every processed frame and
:meth:`Dashboard.on_estimate` / :meth:`Dashboard.on_measurement` for what it publishes, on the
event loop; :func:`serve` runs the server (``[web] listen``) in the daemon's TaskGroup. Drawing
and JPEG encoding happen in the server's own worker thread, only while someone watches.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable

from dffd.config import WebSection
from dffd.mqtt import models
from dffd.step import StepResult
from dffd.web.interface import CallbackSource, FrameView, Snapshot, overlay_from_output
from dffd.web.listen import WebError
from dffd.web.metrics import Metrics
from dffd.web.server import DashboardServer, WebSettings
from drivers.frames import Frame

_LOGGER = logging.getLogger(__name__)


class Dashboard:
    """Buffers and metrics the web server reads; fed by the daemon on the event loop."""

    def __init__(
        self,
        snapshot: Callable[[], Snapshot | None],
        execute: Callable[[bytes], Awaitable[models.CommandReply]],
        *,
        normal_half_px: float,
        counts_range: tuple[int, int] | None,
    ) -> None:
        self.source = CallbackSource(snapshot, execute)
        self.metrics = Metrics(snapshot)
        self.roi: tuple[int, int, int, int] | None = None  # the last acquisition box, drawn
        self._normal_half_px = normal_half_px
        self._counts_range = counts_range
        self._plan: tuple[int, int, int] | None = None

    def on_result(self, frame: Frame, step: StepResult, cpu_s: float) -> None:
        """One processed frame: it becomes the latest video frame with its overlay."""
        self.metrics.observe_frame_cpu(cpu_s)
        if step.output.state != "tracking":
            self._plan = None
        elif step.feedback.plan is not None:
            self._plan = step.feedback.plan
        overlay = overlay_from_output(
            step.output,
            normal_half_px=self._normal_half_px,
            focus_counts=step.tag.focus_counts,
            bracket_counts=self._plan,
            counts_range=self._counts_range,
            roi=self.roi,
            sigma_m=step.feedback.sigma_m,
        )
        self.source.add_frame(FrameView(frame.index, frame.t, frame.image, overlay))

    def on_estimate(self, estimate: models.Estimate, truth_z_m: float | None, now: float) -> None:
        """A published estimate (``now``: monotonic time it was handed to MQTT)."""
        self.source.add_estimate(estimate, truth_z_m)
        self.metrics.observe_publish_latency(now - estimate.t_mono)

    def on_measurement(self, measurement: models.Measurement) -> None:
        """A published burst (rejected ones are listed with their reason)."""
        self.source.add_measurement(measurement)


def settings_for(config: WebSection) -> WebSettings | None:
    """The server settings of ``[web]`` (None: off); raises WebConfigError (e.g. token file)."""
    if config.listen is None:
        return None
    return WebSettings.from_values(config.listen, config.token_file)


async def serve(settings: WebSettings, dashboard: Dashboard) -> None:
    """Serve until cancelled. A port that cannot be bound is logged; the daemon carries on."""
    server = DashboardServer(settings, dashboard.source, dashboard.metrics)
    try:
        await server.start()
    except WebError as exc:
        _LOGGER.warning("dashboard not started: %s", exc)
        return
    try:
        await asyncio.Event().wait()  # until the daemon's shutdown cancels this task
    finally:
        await asyncio.shield(server.stop())
