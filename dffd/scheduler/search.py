"""The search sweep: where pan/tilt looks when automatic acquisition finds no target.

Pure and synchronous (no clock, no I/O): driven by the event times the scheduler is given.

The core searches the whole frame on every frame while it acquires; when that has found nothing
for ``search_after_s`` (armed by an automatic acquisition: ``acquire`` without an ROI, the
service's start without ``[target] roi``, a loss while tracking), the head *sweeps*: it visits
*views* — stare points one field of view apart, overlapping by ``search_overlap``, covering the
camera model's whole pan/tilt range — with one absolute move to each and a dwell of
``search_dwell_s`` there (frames exposed while the head slews are smeared; the dwell gives the
core sharp frames). Order (:func:`search_views`): first the row at the start's tilt, by a doubling
zig-zag in pan from the start (±1, ∓2, ±4, … views: a target near where it was lost is found after
a few views, one anywhere on the row after at most ~3× the travel of a plain sweep), then the
other rows, nearest first, each swept end to end. A centroid ends the sweep at once (the
centring controller takes over). After the last view the head returns to where the sweep began
and holds there for ``search_retry_s`` (the core keeps searching that view), then sweeps again.
``release`` disarms it: a released head never searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from dffd.scheduler.actions import PanTiltAbsolute
from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.geometry import pixel_offset_to_deg

__all__ = ["Search", "SearchStatus", "search_views"]

# Two view centres closer than this (deg) are the same view (a range end on the grid).
SAME_VIEW_DEG = 1e-6

SearchPhase = Literal["waiting", "sweeping", "holding"]


@dataclass(frozen=True, slots=True)
class SearchStatus:
    """Where the search is: ``waiting`` (armed, counting down to a sweep), ``sweeping``
    (``view`` of ``views`` of pass ``pass_number``), ``holding`` (a pass found nothing; the next
    starts at ``next_pass_at``). Times are the scheduler's (the frames' monotonic seconds)."""

    phase: SearchPhase
    pass_number: int
    view: int
    views: int
    started_at: float | None  # when the current (or last) pass began
    next_pass_at: float | None  # waiting/holding: when the next pass starts
    start_deg: tuple[float, float] | None  # where the current (or last) pass began


def search_views(
    start: tuple[float, float],
    pan_range_deg: tuple[float, float],
    tilt_range_deg: tuple[float, float],
    step_deg: tuple[float, float],
    first_direction: int = 1,
) -> list[tuple[float, float]]:
    """The views of one sweep from ``start`` (pan, tilt in deg; not itself a view), covering the
    ranges on a grid through the start (plus the range ends) ``step_deg`` apart; see the module
    docstring for the order. ``first_direction``: +1 the zig-zag first goes to higher pan."""
    pans = _axis(start[0], pan_range_deg, step_deg[0])
    tilts = _axis(start[1], tilt_range_deg, step_deg[1])
    origin_p = min(range(len(pans)), key=lambda i: abs(pans[i] - start[0]))
    origin_t = min(range(len(tilts)), key=lambda i: abs(tilts[i] - start[1]))
    rows = sorted(range(len(tilts)), key=lambda i: (abs(i - origin_t), i < origin_t))
    views: list[tuple[float, float]] = []
    for row in rows:
        if row == origin_t:
            order = _zigzag(origin_p, len(pans), 1 if first_direction >= 0 else -1)
        else:
            here = views[-1][0] if views else start[0]
            ascending = abs(here - pans[0]) <= abs(here - pans[-1])
            order = list(range(len(pans))) if ascending else list(range(len(pans) - 1, -1, -1))
        views.extend((pans[i], tilts[row]) for i in order)
    return [
        v for v in views
        if abs(v[0] - start[0]) > SAME_VIEW_DEG or abs(v[1] - start[1]) > SAME_VIEW_DEG
    ]  # fmt: skip


class Search:
    """The sweep's state machine; :class:`~dffd.scheduler.head.PanTiltHead` drives it."""

    def __init__(self, config: SchedulerConfig) -> None:
        self.config = config
        self.armed = False
        self._rearm_on_sight = False  # an ROI acquisition: armed once the target was seen
        self._unseen_since = -math.inf
        self._hold_until = -math.inf
        self._passes = 0
        self._sweep: _Sweep | None = None
        self._last: _Sweep | None = None  # the last pass (for the holding status)
        self._direction = 1  # the zig-zag's first direction: the target's last pan motion

    @property
    def enabled(self) -> bool:
        """The configuration allows sweeps (a delay and the head's ranges are known)."""
        cfg = self.config
        return (
            cfg.search_after_s is not None
            and cfg.pan_range_deg is not None
            and cfg.tilt_range_deg is not None
            and cfg.pan_tilt_mode != "off"
        )

    @property
    def sweeping(self) -> bool:
        """A pass is under way."""
        return self._sweep is not None

    def arm(self, t: float) -> None:
        """Automatic acquisition from ``t`` on: sweep if nothing is seen for ``search_after_s``."""
        self.armed = self.enabled
        self._rearm_on_sight = False
        self._restart(t)

    def disarm(self, *, until_seen: bool = False) -> None:
        """No sweeps (released; or, ``until_seen``, acquiring in an ROI until the target shows)."""
        self.armed = False
        self._rearm_on_sight = until_seen and self.enabled
        self._sweep = None

    def seen(self, t: float, pan_rate_deg_s: float = 0.0) -> None:
        """The core sees the target (centroid of the frame exposed at ``t``): any pass ends."""
        if self._rearm_on_sight:
            self.armed, self._rearm_on_sight = True, False
        if pan_rate_deg_s:
            self._direction = 1 if pan_rate_deg_s > 0 else -1
        self._restart(t)

    def restart_timer(self, t: float) -> None:
        """Count ``search_after_s`` from ``t`` (the head just returned to where it last saw the
        target and holds there)."""
        if self._sweep is None:
            self._unseen_since = max(self._unseen_since, t)

    def on_move_done(self, t: float) -> None:
        """The outstanding pan/tilt action ended at ``t`` (Completion, answer or failure)."""
        sweep = self._sweep
        if sweep is not None and sweep.moving:
            sweep.moving = False
            sweep.dwell_until = t + self.config.search_dwell_s

    def decide(
        self, now: float, here: tuple[float, float], speeds: tuple[int, int]
    ) -> tuple[PanTiltAbsolute | None, float]:
        """The sweep's move due at ``now`` (None: none) and when to look again (inf: on an event).

        ``here``: the head model's pan/tilt now; ``speeds``: the absolute moves' speed codes.
        """
        if not self.armed:
            return None, math.inf
        cfg = self.config
        if self._sweep is None:
            assert cfg.search_after_s is not None
            start_at = max(self._unseen_since + cfg.search_after_s, self._hold_until)
            if now < start_at:
                return None, start_at
            self._begin(now, here)
        sweep = self._sweep
        assert sweep is not None
        if sweep.moving:
            return None, math.inf
        if sweep.dwell_until is not None and now < sweep.dwell_until:
            return None, sweep.dwell_until
        if sweep.index < len(sweep.views):
            pan, tilt = sweep.views[sweep.index]
            sweep.index += 1
            sweep.moving = True
            sweep.dwell_until = None
            return PanTiltAbsolute(pan, tilt, *speeds), math.inf
        # The pass found nothing: back to where it began, hold, then sweep again.
        self._last, self._sweep = sweep, None
        self._hold_until = now + cfg.search_retry_s
        return PanTiltAbsolute(sweep.start[0], sweep.start[1], *speeds), self._hold_until

    def status(self) -> SearchStatus | None:
        """The search now (None when not armed)."""
        if not self.armed:
            return None
        sweep = self._sweep
        if sweep is not None:
            return SearchStatus(
                "sweeping", self._passes, sweep.index, len(sweep.views), sweep.started_at,
                None, sweep.start,
            )  # fmt: skip
        last = self._last
        after = self.config.search_after_s or 0.0
        if last is not None and self._hold_until > -math.inf:
            return SearchStatus(
                "holding", self._passes, len(last.views), len(last.views), last.started_at,
                max(self._hold_until, self._unseen_since + after), last.start,
            )  # fmt: skip
        return SearchStatus("waiting", self._passes, 0, 0, None, self._unseen_since + after, None)

    def _restart(self, t: float) -> None:
        self._unseen_since = t
        self._hold_until = -math.inf
        self._sweep = None
        self._last = None
        self._passes = 0

    def _begin(self, now: float, here: tuple[float, float]) -> None:
        cfg = self.config
        assert cfg.pan_range_deg is not None
        assert cfg.tilt_range_deg is not None
        start = (
            min(max(here[0], cfg.pan_range_deg[0]), cfg.pan_range_deg[1]),
            min(max(here[1], cfg.tilt_range_deg[0]), cfg.tilt_range_deg[1]),
        )
        views = search_views(
            start, cfg.pan_range_deg, cfg.tilt_range_deg, view_step_deg(cfg), self._direction
        )
        self._passes += 1
        self._sweep = _Sweep(views, start, now)


def view_step_deg(config: SchedulerConfig) -> tuple[float, float]:
    """Pan and tilt between neighbouring views: the field of view less the overlap."""
    w, h = config.frame_size
    keep = 1.0 - config.search_overlap
    f, pitch = config.focal_length_mm, config.pixel_pitch_mm
    return (
        2.0 * pixel_offset_to_deg(w / 2.0, f, pitch) * keep,
        2.0 * pixel_offset_to_deg(h / 2.0, f, pitch) * keep,
    )


@dataclass
class _Sweep:
    """One pass: its views, the next one's index, and the move or dwell under way."""

    views: list[tuple[float, float]]
    start: tuple[float, float]
    started_at: float
    index: int = 0
    moving: bool = False
    dwell_until: float | None = None


def _axis(origin: float, span: tuple[float, float], step: float) -> list[float]:
    """View centres along one axis: ``origin`` + k·``step`` within ``span``, and its ends."""
    lo, hi = span
    origin = min(max(origin, lo), hi)
    below = math.floor((origin - lo) / step + SAME_VIEW_DEG)
    above = math.floor((hi - origin) / step + SAME_VIEW_DEG)
    centres = [origin + k * step for k in range(-below, above + 1)]
    if centres[0] - lo > SAME_VIEW_DEG:
        centres.insert(0, lo)
    if hi - centres[-1] > SAME_VIEW_DEG:
        centres.append(hi)
    return centres


def _zigzag(origin: int, n: int, direction: int) -> list[int]:
    """Indices 0…n−1 from ``origin`` outwards, the reach doubling at each turn (cow path)."""
    order = [origin]
    low = high = origin
    reach = 1
    while low > 0 or high < n - 1:
        if direction > 0 and high < n - 1:
            new = min(n - 1, origin + reach)
            order.extend(range(high + 1, new + 1))
            high = new
        elif direction < 0 and low > 0:
            new = max(0, origin - reach)
            order.extend(range(low - 1, new - 1, -1))
            low = new
        direction = -direction
        reach *= 2
    return order
