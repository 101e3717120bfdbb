"""Status of the running daemon: achieved rates and the link's health, as payloads and rows."""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

from dffd import __version__
from dffd.daemon.console import ConsoleSnapshot
from dffd.daemon.payloads import nonneg
from dffd.mqtt import models
from drivers.stream import StreamFrameSource

if TYPE_CHECKING:
    from dffd.core.pipeline import Measurement
    from dffd.scheduler import SearchStatus
    from drivers.visca.link import ViscaLink

# Window over which achieved rates are computed.
RATE_WINDOW_S = 5.0
# Frames flow if the last one is younger than this (watchdog pings and READY depend on it).
FRAMES_FLOWING_S = 1.0
# Nominal bracket spacing (counts) for the rate limit until the core plans a burst.
DEFAULT_SPACING_COUNTS = 300

__all__ = [
    "DEFAULT_SPACING_COUNTS",
    "FRAMES_FLOWING_S",
    "RATE_WINDOW_S",
    "RateMeter",
    "StatusBoard",
    "link_health",
    "video_health",
]


class StatusBoard:
    """What the status reports, as the shell sees it happen: rates, bursts, the last estimate."""

    def __init__(self, camera_name: str, best: models.EstimatorName, t_start: float) -> None:
        self.camera_name = camera_name
        self.best = best
        self.t_start = t_start
        self.frames = RateMeter()
        self.estimates = RateMeter()
        self.measurements = RateMeter()
        self.bursts_accepted = 0
        self.bursts_rejected = 0
        self.state = "acquiring"
        self.message: str | None = None  # what the operator should know (status, dashboard)
        self.last_frame_mono: float | None = None
        self.last_estimate_mono: float | None = None  # None: none since start or release
        self.last_depth: dict[str, float | None] = {}
        self.last_truth_z: float | None = None
        self.last_size: float | None = None
        self.spacing = DEFAULT_SPACING_COUNTS  # half the burst bracket (counts), for the limit
        self.known_size_m: float | None = None  # what CF1 is told (config or set_known_size)
        self.last_measured: tuple[float, float] | None = None  # (monotonic, z_m) of a burst
        self.search: SearchStatus | None = None  # the scheduler's search sweep, if armed

    def on_frame(self, now: float) -> None:
        """A frame was delivered at ``now``."""
        self.last_frame_mono = now
        self.frames.add(now)

    def on_measurement(self, now: float, measurement: Measurement) -> None:
        """The core closed a burst."""
        if measurement.accepted:
            self.bursts_accepted += 1
            if measurement.z_m is not None and math.isfinite(measurement.z_m):
                self.last_measured = (now, float(measurement.z_m))
        else:
            self.bursts_rejected += 1
        self.measurements.add(now)

    def on_estimate(self, now: float, estimate: models.Estimate) -> None:
        """An estimate was published."""
        self.estimates.add(now)
        self.last_depth = dict(estimate.depth_m.model_dump())
        self.last_size = estimate.size_m
        self.last_estimate_mono = now

    def on_acquire(self, roi: tuple[int, int, int, int] | None = None) -> None:
        """An acquire command: the core searches for the target (said until it tracks it)."""
        self.state = "acquiring"
        if roi is None:
            self.message = (
                "acquire: searching the whole frame for the target; if it is not in view, "
                "pan/tilt sweeps the camera's range for it"
            )
        else:
            self.message = (
                f"acquire: searching roi {list(roi)} for the target (no sweep: the box is in "
                "this view)"
            )

    def on_release(self) -> None:
        """A release command: idle, and the last depths are no longer current."""
        self.state = "idle"
        self.message = "released by command: no depths until an acquire command"
        self.last_estimate_mono = None
        self.last_depth = {}
        self.last_measured = None

    def search_payload(self, now: float) -> models.Search | None:
        """The status's ``search`` block (None unless the search is armed and no target is
        followed)."""
        s = self.search
        if s is None or self.state == "tracking":
            return None
        return models.Search(
            phase=s.phase,
            pass_number=s.pass_number,
            view=s.view,
            views=s.views,
            elapsed_s=None if s.started_at is None else max(0.0, now - s.started_at),
            next_pass_in_s=None if s.next_pass_at is None else max(0.0, s.next_pass_at - now),
        )

    def search_message(self, now: float) -> str | None:
        """What the operator reads about the sweep (None unless sweeping or holding)."""
        s = self.search_payload(now)
        if s is None or s.phase == "waiting":
            return None
        if s.phase == "sweeping":
            return (
                f"searching: the target is not in view; pan/tilt sweeps the camera's range, view "
                f"{s.view} of {s.views} (sweep {s.pass_number}, {s.elapsed_s or 0.0:.0f} s); "
                "'release' stops it"
            )
        return (
            f"searching: a whole sweep ({s.views} views) found no target; holding where it "
            f"began, next sweep in {s.next_pass_in_s or 0.0:.0f} s; 'release' stops it"
        )

    def estimate_age(self, now: float) -> float | None:
        """Seconds since the last published estimate (None: none since start or release)."""
        last = self.last_estimate_mono
        return None if last is None else max(0.0, now - last)

    def on_plan(self, plan: tuple[int, int, int]) -> None:
        """The core planned a burst (its spacing sets the depth-rate limit)."""
        self.spacing = max(1, (max(plan) - min(plan)) // 2)

    def frames_flowing(self, now: float) -> bool:
        """A frame arrived within :data:`FRAMES_FLOWING_S`."""
        last = self.last_frame_mono
        return last is not None and now - last < FRAMES_FLOWING_S

    def status(
        self,
        now: float,
        *,
        depth_limit_hz: float | None,
        link: models.LinkHealth,
        mqtt: models.MqttHealth,
        drops: models.Drops,
        video: models.VideoHealth | None = None,
    ) -> models.Status:
        """The retained ``…/status`` payload now."""
        return models.Status(
            availability="online",
            t=models.wall_time(),
            t_mono=now,
            state=self.state,  # type: ignore[arg-type]
            camera=self.camera_name,
            last_estimate_age_s=self.estimate_age(now),
            message=self.search_message(now) or self.message,
            search=self.search_payload(now),
            rates=models.Rates(
                frame_hz=self.frames.rate(now),
                estimate_hz=self.estimates.rate(now),
                depth_hz=self.measurements.rate(now),
                depth_limit_hz=nonneg(depth_limit_hz),
            ),
            link=link,
            video=video,
            mqtt=mqtt,
            drops=drops,
            version=__version__,
        )

    def snapshot(
        self,
        now: float,
        status: models.Status,
        *,
        roles: dict[str, int],
        pan_tilt_deg: tuple[float, float],
    ) -> ConsoleSnapshot:
        """The console's view of ``status`` and the board."""
        rates, link, mqtt, drops = status.rates, status.link, status.mqtt, status.drops
        depth_m = dict(self.last_depth)
        measured_age_s = None
        if self.last_measured is not None:
            # Depth measurements come per burst (~2 Hz), so the estimate of the moment rarely
            # carries one: show the last accepted one with its age instead of a bare dash.
            measured_age_s = max(0.0, now - self.last_measured[0])
            depth_m["measured"] = self.last_measured[1]
        assert rates is not None
        assert link is not None
        assert mqtt is not None
        assert drops is not None
        return ConsoleSnapshot(
            camera=self.camera_name,
            state=self.state,
            uptime_s=now - self.t_start,
            frame_hz=rates.frame_hz,
            estimate_hz=rates.estimate_hz,
            depth_hz=rates.depth_hz,
            depth_limit_hz=rates.depth_limit_hz,
            link_connected=link.connected,
            link_timeouts=link.timeouts,
            link_errors=link.errors,
            link_reconnects=link.reconnects,
            mqtt_connected=mqtt.connected,
            mqtt_backlog=mqtt.backlog,
            frames_dropped=drops.frames,
            bursts_accepted=self.bursts_accepted,
            bursts_rejected=self.bursts_rejected,
            roles=roles,
            depth_m=depth_m,
            measured_age_s=measured_age_s,
            last_estimate_age_s=status.last_estimate_age_s,
            best=self.best,
            truth_z_m=self.last_truth_z,
            size_m=self.last_size,
            pan_deg=pan_tilt_deg[0],
            tilt_deg=pan_tilt_deg[1],
            known_size_m=self.known_size_m,
            search=_search_short(status.search),
        )


def _search_short(search: models.Search | None) -> str | None:
    """The console's few words on the sweep."""
    if search is None or search.phase == "waiting":
        return None
    if search.phase == "sweeping":
        return f"searching: view {search.view}/{search.views}, sweep {search.pass_number}"
    return f"search found nothing; next sweep in {search.next_pass_in_s or 0.0:.0f} s"


class RateMeter:
    """Events per second over a sliding window (bounded memory)."""

    def __init__(self, window_s: float = RATE_WINDOW_S, max_events: int = 4096) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque(maxlen=max_events)
        self.count = 0

    def add(self, t: float) -> None:
        """Record one event at ``t``."""
        self._times.append(t)
        self.count += 1

    def rate(self, now: float) -> float:
        """Events per second over the window ending at ``now``."""
        while self._times and now - self._times[0] > self.window_s:
            self._times.popleft()
        if len(self._times) < 2:
            return 0.0
        span = max(now - self._times[0], self._times[-1] - self._times[0])
        return (len(self._times) - 1) / span if span > 0 else 0.0


def link_health(link: ViscaLink | None, now: float) -> models.LinkHealth:
    """The ``link`` block of the status (not connected when there is no link yet)."""
    if link is None:
        return models.LinkHealth(connected=False)
    h = link.health()
    age = None if h.last_reply_monotonic is None else max(0.0, now - h.last_reply_monotonic)
    return models.LinkHealth(
        connected=h.connected,
        bytes_in=h.bytes_in,
        bytes_out=h.bytes_out,
        replies=sum(h.replies.values()),
        errors=sum(h.errors_by_code.values()),
        timeouts=sum(h.timeouts.values()),
        last_reply_age_s=age,
        reconnects=h.reconnects,
        ip_retransmits=None if h.ip is None else h.ip.retransmits,
        ip_given_up=None if h.ip is None else h.ip.given_up,
        ip_sequence_errors=None if h.ip is None else h.ip.sequence_errors,
        ip_resets=None if h.ip is None else h.ip.resets,
    )


def video_health(source: object) -> models.VideoHealth | None:
    """The ``video`` block of the status: a network stream's health (None for other sources)."""
    if not isinstance(source, StreamFrameSource):
        return None
    h = source.health()
    return models.VideoHealth(
        url=h.url,
        connected=h.connected,
        frames=h.frames,
        reconnects=h.reconnects,
        stream_timestamps=h.stream_timestamps,
        latency_s=h.latency_s,
    )
