"""The shell's view of the scheduler's search sweep: a log line at each turn, the status board.

The sweep itself is the pure scheduler's (:mod:`dffd.scheduler.search`); this only watches its
status after every scheduler step and says what changed: when a sweep starts (with its extent),
when the target is found, when a whole sweep found nothing (WARNING: the head then holds where the
sweep began until the next one). The lock-step bench watches its scheduler with it too (no status
board there), so a bench run logs its sweeps as the service does.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dffd.daemon.status import StatusBoard
    from dffd.scheduler import Scheduler, SearchStatus

_LOGGER = logging.getLogger(__name__)

__all__ = ["SearchWatch"]


class SearchWatch:
    """Follows ``scheduler.search_status`` into ``board.search`` (if a board) and the log."""

    def __init__(self, scheduler: Scheduler, board: StatusBoard | None = None) -> None:
        self.scheduler = scheduler
        self.board = board
        self._last: SearchStatus | None = None

    def update(self, now: float) -> bool:
        """Look at the search after a scheduler step at ``now``; log a change of phase and
        return True then (the shell publishes the status at once)."""
        status = self.scheduler.search_status
        last, self._last = self._last, status
        if self.board is not None:
            self.board.search = status
        before = None if last is None else last.phase
        after = None if status is None else status.phase
        if before == after:
            return False
        if after == "sweeping" and status is not None:
            self._started(status)
        elif before == "sweeping" and after is None and self.scheduler.search_armed:
            assert last is not None
            elapsed = 0.0 if last.started_at is None else now - last.started_at
            _LOGGER.info(
                "search: target in view after %d of %d views (%.1f s of sweeping); following it",
                last.view, last.views, elapsed,
            )  # fmt: skip
        elif after == "holding" and status is not None:
            elapsed = 0.0 if status.started_at is None else now - status.started_at
            wait = 0.0 if status.next_pass_at is None else status.next_pass_at - now
            pan, tilt = status.start_deg or (0.0, 0.0)
            _LOGGER.warning(
                "search: no target after a whole sweep (%d views, %.0f s); holding at pan "
                "%+.1f°, tilt %+.1f°, where it began (the core keeps searching that view); next "
                "sweep in %.0f s; 'release' stops it",
                status.views, elapsed, pan, tilt, wait,
            )  # fmt: skip
        return True

    def _started(self, status: SearchStatus) -> None:
        cfg = self.scheduler.config
        pan, tilt = status.start_deg or (0.0, 0.0)
        pans = cfg.pan_range_deg or (0.0, 0.0)
        tilts = cfg.tilt_range_deg or (0.0, 0.0)
        _LOGGER.info(
            "search: no target for %g s of automatic acquisition: sweep %d of pan/tilt over pan "
            "%+.0f…%+.0f°, tilt %+.0f…%+.0f° from pan %+.1f°, tilt %+.1f° (%d views, %.1f s "
            "dwell each, nearest first); 'release' stops it",
            cfg.search_after_s or 0.0, status.pass_number, pans[0], pans[1], tilts[0], tilts[1],
            pan, tilt, status.views, cfg.search_dwell_s,
        )  # fmt: skip
