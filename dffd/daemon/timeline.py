"""The start-up timeline of ``dffd run``: each step logged once, in seconds since the process began.

``python -m dffd -vv run`` (or ``[log] level = "DEBUG"``) then shows where a start's seconds go —
imports, the broker, the camera's VISCA initialisation, the first frame, the first estimate and
the first depth the daemon publishes (docs/design.md §5.3) — on the same clock as
``hil.bench_start``, which times from the process start.
"""

from __future__ import annotations

import logging
import os
import time

__all__ = ["StartTimeline", "process_start_monotonic"]

_LOGGER = logging.getLogger(__name__)


def process_start_monotonic() -> float:
    """``time.monotonic()`` at the moment this process started (Linux: from /proc; elsewhere
    the first call's time, i.e. later than the truth)."""
    now = time.monotonic()
    try:
        with open("/proc/self/stat", "rb") as stat:  # noqa: PTH123 - one small read
            fields = stat.read().rsplit(b")", 1)[1].split()
        # starttime (field 22, clock ticks after boot) is the 20th after the command's ")"
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - started
    except (OSError, ValueError, IndexError, AttributeError):
        return now
    return now - max(0.0, age)


class StartTimeline:
    """Logs each named start-up step once, at DEBUG, with its time since the process start."""

    def __init__(self) -> None:
        self.t0 = process_start_monotonic()
        self._seen: set[str] = set()

    def mark(self, step: str) -> None:
        """Log ``step`` (the first time only)."""
        if step in self._seen:
            return
        self._seen.add(step)
        self.event(step)

    def marked(self, step: str) -> bool:
        """Whether ``step`` has been marked."""
        return step in self._seen

    def event(self, what: str) -> None:
        """Log ``what`` with its time since the process start (every time)."""
        _LOGGER.debug("start-up %.3f s: %s", time.monotonic() - self.t0, what)
