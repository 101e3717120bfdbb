"""Shared physical state of the simulated camera: motors as functions of time.

The simulated VISCA device writes it (commands start and stop motors); the optics renderer reads
it (where were pan, tilt, focus and zoom during an exposure, and did anything move). Each axis
keeps a short history of constant-velocity segments so that a frame exposed in the recent past
(capture latency) is rendered with the positions that held then, not now.

Time is whatever the injected clock says: ``time.monotonic`` live, a virtual clock in lock-step
benchmarks.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

Clock = Callable[[], float]

# Segments kept per axis. At ≤ 60 commands/s (one per video field) this covers > 1 s of history,
# far more than any capture latency.
HISTORY_SEGMENTS = 128


@dataclass(frozen=True, slots=True)
class _Segment:
    t_start: float
    start: float
    velocity: float  # units per second, signed
    t_stop: float  # when the motion ends (math.inf while driving without a target)
    end: float  # exact position once stopped, so a finished move lands on its target


class Axis:
    """One motor axis between hard limits; position is piecewise linear in time."""

    def __init__(self, name: str, position: float, low: float, high: float, t: float) -> None:
        if not low <= position <= high:
            raise ValueError(f"{name} initial position {position} outside [{low}, {high}]")
        self.name = name
        self.low = low
        self.high = high
        self._segments: deque[_Segment] = deque(maxlen=HISTORY_SEGMENTS)
        self._segments.append(_Segment(t, position, 0.0, t, position))

    def position(self, t: float) -> float:
        """Position at time ``t`` (clamped to the limits)."""
        seg = self._segment_at(t)
        if t >= seg.t_stop:
            return seg.end
        dt = t - seg.t_start
        return min(self.high, max(self.low, seg.start + seg.velocity * max(0.0, dt)))

    def moving(self, t: float) -> bool:
        """True while the motor turns at time ``t``."""
        seg = self._segment_at(t)
        return seg.velocity != 0.0 and seg.t_start <= t < seg.t_stop

    def moved_between(self, t0: float, t1: float) -> bool:
        """True if the motor turned at any time in ``[t0, t1]``."""
        return any(
            s.velocity != 0.0 and s.t_start < t1 and s.t_stop > t0 for s in self._segments
        ) or self.moving(t0)

    def arrival_time(self) -> float:
        """When the current motion ends (``inf`` while driving without a target)."""
        return self._segments[-1].t_stop

    def move_to(self, target: float, speed: float, t: float) -> float:
        """Move to ``target`` at ``speed`` (units/s) from time ``t``; return the arrival time."""
        if speed <= 0.0:
            raise ValueError(f"{self.name} speed must be positive, got {speed}")
        target = min(self.high, max(self.low, target))
        here = self.position(t)
        distance = target - here
        duration = abs(distance) / speed
        velocity = math.copysign(speed, distance) if distance else 0.0
        self._segments.append(_Segment(t, here, velocity, t + duration, target))
        return t + duration

    def drive(self, direction: int, speed: float, t: float) -> None:
        """Turn continuously at ``speed`` towards ``direction`` (+1/−1) until stopped or a limit."""
        if direction not in (1, -1):
            raise ValueError(f"{self.name} direction must be +1 or -1, got {direction}")
        here = self.position(t)
        limit = self.high if direction > 0 else self.low
        t_stop = t + abs(limit - here) / speed if speed > 0 else t
        self._segments.append(_Segment(t, here, direction * speed, t_stop, limit))

    def stop(self, t: float) -> None:
        """Stop at time ``t`` where the motor is then."""
        here = self.position(t)
        self._segments.append(_Segment(t, here, 0.0, t, here))

    def jump(self, position: float, t: float) -> None:
        """Set the position instantly (power-up, reset)."""
        here = min(self.high, max(self.low, position))
        self._segments.append(_Segment(t, here, 0.0, t, here))

    def _segment_at(self, t: float) -> _Segment:
        for seg in reversed(self._segments):
            if seg.t_start <= t:
                return seg
        return self._segments[0]  # older than the history: the oldest known state


@dataclass(frozen=True, slots=True)
class CameraSnapshot:
    """Positions at one instant, in the simulator's physical units."""

    t: float
    pan_deg: float
    tilt_deg: float
    focus_counts: float
    zoom_counts: float
    pan_tilt_moving: bool
    focus_moving: bool
    zoom_moving: bool
    powered: bool


@dataclass
class CameraState:
    """Pan/tilt (degrees), focus and zoom (counts) of the simulated camera, thread-safe.

    The VISCA device mutates it from the event loop; renderers may read it from other threads.
    """

    clock: Clock = time.monotonic
    pan_limits_deg: tuple[float, float] = (-100.0, 100.0)
    tilt_limits_deg: tuple[float, float] = (-25.0, 25.0)
    focus_limits: tuple[float, float] = (0x1000, 0x8400)
    zoom_limits: tuple[float, float] = (0x0000, 0x4000)
    initial_focus: float = 0x1000
    initial_zoom: float = 0x0000
    powered: bool = True
    autofocus: bool = False
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    def __post_init__(self) -> None:
        now = self.clock()
        self.pan = Axis("pan", 0.0, *self.pan_limits_deg, t=now)
        self.tilt = Axis("tilt", 0.0, *self.tilt_limits_deg, t=now)
        self.focus = Axis("focus", self.initial_focus, *self.focus_limits, t=now)
        self.zoom = Axis("zoom", self.initial_zoom, *self.zoom_limits, t=now)

    def set_limits(
        self,
        *,
        pan_deg: tuple[float, float],
        tilt_deg: tuple[float, float],
        focus: tuple[float, float],
        zoom: tuple[float, float],
    ) -> None:
        """Change the end stops (a camera model's); positions outside are clamped into them."""
        with self.lock:
            now = self.clock()
            self.pan_limits_deg, self.tilt_limits_deg = pan_deg, tilt_deg
            self.focus_limits, self.zoom_limits = focus, zoom
            for axis, (low, high) in (
                (self.pan, pan_deg), (self.tilt, tilt_deg), (self.focus, focus), (self.zoom, zoom),
            ):  # fmt: skip
                if (axis.low, axis.high) != (low, high):
                    position = axis.position(now)
                    axis.low, axis.high = low, high
                    axis.jump(position, now)

    def now(self) -> float:
        """The state's clock."""
        return self.clock()

    def snapshot(self, t: float | None = None) -> CameraSnapshot:
        """Positions and motion flags at time ``t`` (default: now)."""
        with self.lock:
            at = self.clock() if t is None else t
            return CameraSnapshot(
                t=at,
                pan_deg=self.pan.position(at),
                tilt_deg=self.tilt.position(at),
                focus_counts=self.focus.position(at),
                zoom_counts=self.zoom.position(at),
                pan_tilt_moving=self.pan.moving(at) or self.tilt.moving(at),
                focus_moving=self.focus.moving(at),
                zoom_moving=self.zoom.moving(at),
                powered=self.powered,
            )
