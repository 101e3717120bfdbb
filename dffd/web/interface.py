"""What the dashboard needs from a running daemon: one Protocol and the plain data it returns.

The web package never reaches into the daemon: the daemon implements :class:`DashboardSource`
(usually by keeping a :class:`DashboardFeed` for the buffered parts) and hands it to
:class:`~dffd.web.server.DashboardServer`. Every method is called on the event loop and must
return at once: no I/O, no waiting on the estimator thread (commands excepted, which are async).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from dffd.core.pipeline import PipelineOutput
from dffd.mqtt import models

# Estimates kept for the plots: 60 s at the 30 fps the tracking frames can reach.
ESTIMATE_HISTORY_MAX: Final = 1800
# Rejected bursts kept for the status panel: the last few are what an operator reads.
REJECTIONS_MAX: Final = 20

ESTIMATOR_NAMES: Final = ("lpv", "kf", "cf2", "cf1", "measured")


@dataclass(frozen=True, slots=True)
class Overlay:
    """What the estimator knows about one frame, to be drawn on it (pixels, focus counts)."""

    state: str
    contour_px: npt.NDArray[np.float64] | None = None  # (N, 2) closed contour, image coordinates
    normal_half_px: float = 0.0  # half-length of the search normals drawn at the contour points
    centroid_px: tuple[float, float] | None = None
    roi: tuple[int, int, int, int] | None = None  # pending/last acquisition box [x, y, w, h]
    focus_counts: int | None = None  # focus setting during the exposure
    bracket_counts: tuple[int, ...] | None = None  # the planned burst settings
    counts_range: tuple[int, int] | None = None  # the lens's focus range, for the bracket bar
    z_m: float | None = None
    sigma_m: float | None = None


def overlay_from_output(
    output: PipelineOutput,
    *,
    normal_half_px: float,
    focus_counts: int | None = None,
    bracket_counts: tuple[int, ...] | None = None,
    counts_range: tuple[int, int] | None = None,
    roi: tuple[int, int, int, int] | None = None,
    sigma_m: float | None = None,
) -> Overlay:
    """The overlay of one core output (its contour and centroid, the last best estimate)."""
    obs = output.observation
    est = output.estimate
    return Overlay(
        state=output.state,
        contour_px=None if obs is None else np.asarray(obs.points, dtype=np.float64),
        normal_half_px=normal_half_px,
        centroid_px=None if obs is None else (float(obs.centroid[0]), float(obs.centroid[1])),
        roi=roi,
        focus_counts=focus_counts,
        bracket_counts=bracket_counts,
        counts_range=counts_range,
        z_m=None if est is None else est.z_m,
        sigma_m=sigma_m if est is None or est.sigma_m is None else est.sigma_m,
    )


@dataclass(frozen=True, slots=True)
class FrameView:
    """The latest frame with its overlay; the image is never modified by the dashboard."""

    index: int
    t_mono: float  # exposure time, monotonic s
    image: npt.NDArray[np.uint8]  # H×W gray or H×W×3 BGR
    overlay: Overlay


@dataclass(frozen=True, slots=True)
class EstimatePoint:
    """One published estimate with the simulator's truth at its frame (None on hardware)."""

    estimate: models.Estimate
    truth_z_m: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The compact form the page plots."""
        e = self.estimate
        return {
            "seq": e.seq,
            "t": e.t_mono,
            "state": e.state,
            "best": e.best,
            "z": e.z_m,
            "sigma": e.sigma_m,
            "d": e.depth_m.model_dump(),
            "truth": self.truth_z_m,
            # The 3D tracker's (None without a track): world frame, docs/tracking3d.md.
            "pos": e.position_m,
            "vel": e.velocity_m_s,
            "acc": e.acceleration_m_s2,
            "omega": e.angular_speed_rad_s,
            "pos_sigma": e.position_sigma_m,
            "probs": e.model_probabilities,
        }


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The daemon's state now, for the status panel and ``/metrics``."""

    status: models.Status  # the ``…/status`` payload as it would be published now
    last_estimate_age_s: float | None  # None: no estimate yet (or none since a release)
    bursts_accepted: int = 0
    bursts_rejected: int = 0
    frame_size: tuple[int, int] | None = None  # (width, height) px
    message: str | None = None  # what the operator should know (e.g. "released: idle")


@runtime_checkable
class DashboardSource(Protocol):
    """Implemented by the daemon (and by the tests' in-process stand-in)."""

    def latest_frame(self) -> FrameView | None:
        """The newest frame with its overlay, or None before the first frame."""
        ...

    def snapshot(self) -> Snapshot | None:
        """The state now, or None while the daemon is still starting."""
        ...

    def estimates_after(self, seq: int) -> Sequence[EstimatePoint]:
        """Buffered estimates with ``seq`` greater than ``seq``, oldest first (bounded)."""
        ...

    def rejections(self) -> Sequence[models.Measurement]:
        """The most recent rejected bursts, oldest first (bounded)."""
        ...

    async def execute(self, payload: bytes) -> models.CommandReply:
        """Run one JSON command through the MQTT command path; same validation, same reply."""
        ...


class DashboardFeed:
    """Bounded buffers behind the data half of :class:`DashboardSource`; fed on the event loop."""

    def __init__(
        self, history_max: int = ESTIMATE_HISTORY_MAX, rejections_max: int = REJECTIONS_MAX
    ) -> None:
        self._frame: FrameView | None = None
        self._estimates: deque[EstimatePoint] = deque(maxlen=history_max)
        self._rejections: deque[models.Measurement] = deque(maxlen=rejections_max)

    def add_frame(self, view: FrameView) -> None:
        """Replace the latest frame (the previous one is dropped: the video shows the newest)."""
        self._frame = view

    def add_estimate(self, estimate: models.Estimate, truth_z_m: float | None = None) -> None:
        """Append a published estimate (drops the oldest beyond the bound)."""
        self._estimates.append(EstimatePoint(estimate, truth_z_m))

    def add_measurement(self, measurement: models.Measurement) -> None:
        """Keep a burst if its fit was rejected."""
        if not measurement.fit.accepted:
            self._rejections.append(measurement)

    def clear_frame(self) -> None:
        """Forget the latest frame (e.g. capture stopped): nothing stale is shown as live."""
        self._frame = None

    def latest_frame(self) -> FrameView | None:
        """See :meth:`DashboardSource.latest_frame`."""
        return self._frame

    def estimates_after(self, seq: int) -> list[EstimatePoint]:
        """See :meth:`DashboardSource.estimates_after`."""
        out: list[EstimatePoint] = []
        for point in reversed(self._estimates):
            if point.estimate.seq <= seq:
                break
            out.append(point)
        out.reverse()
        return out

    def rejections(self) -> list[models.Measurement]:
        """See :meth:`DashboardSource.rejections`."""
        return list(self._rejections)


class CallbackSource(DashboardFeed):
    """A complete :class:`DashboardSource`: a feed plus the daemon's snapshot and command path."""

    def __init__(
        self,
        snapshot: Callable[[], Snapshot | None],
        execute: Callable[[bytes], Awaitable[models.CommandReply]],
        *,
        history_max: int = ESTIMATE_HISTORY_MAX,
        rejections_max: int = REJECTIONS_MAX,
    ) -> None:
        super().__init__(history_max, rejections_max)
        self._snapshot = snapshot
        self._execute = execute

    def snapshot(self) -> Snapshot | None:
        """See :meth:`DashboardSource.snapshot`."""
        return self._snapshot()

    async def execute(self, payload: bytes) -> models.CommandReply:
        """See :meth:`DashboardSource.execute`."""
        return await self._execute(payload)
