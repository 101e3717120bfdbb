"""The scheduler's counters, for status and tests."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(slots=True)
class SchedulerStats:
    """Counters for status and tests."""

    frames: dict[str, int] = field(default_factory=lambda: {"track": 0, "burst": 0, "transit": 0})
    bursts_started: int = 0
    bursts_completed: int = 0
    bursts_incomplete: int = 0
    rolling_openings: int = 0  # rolling ends with no previous end to close a burst with
    focus_moves: int = 0
    focus_failures: int = 0
    focus_inquiries: int = 0
    pan_tilt_commands: int = 0
    pan_tilt_failures: int = 0
