"""Focus history: the intervals over which the focus was stationary, for tagging frames.

The focus is *stationary* from the moment a Completion is received (the motor stopped before the
camera said so) until the next move is issued (the lens cannot move before its command is
written). A frame is ``track``/``burst`` only if its whole exposure lies inside one of those
intervals with ``timing_margin_s`` to spare, otherwise ``transit``. Where that is not certain (a
move timed out or failed, or the start-up position is unknown) the scheduler issues focus
inquiries until two readings agree (or one equals the commanded target) and tags ``transit``
meanwhile.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from dffd.scheduler.clock import TIME_EPS_S

# Stationary-focus intervals kept for tagging late frames: at one move per frame this still covers
# several seconds, far more than any capture latency.
FOCUS_HISTORY = 64


@dataclass(slots=True)
class Move:
    """A focus move issued and not yet settled."""

    move_id: int
    target: int
    t_issued: float
    t_done: float = math.inf  # predicted Completion (``focus_move_time_s``); inf: unknown


class FocusHistory:
    """The recent stationary-focus intervals (dwells), newest last."""

    def __init__(self, timing_margin_s: float) -> None:
        self._dwells: deque[_Dwell] = deque(maxlen=FOCUS_HISTORY)
        self._timing_margin_s = timing_margin_s

    def settle(self, t: float, counts: int) -> None:
        """The focus is stationary at ``counts`` from ``t`` on (until :meth:`release`)."""
        self._dwells.append(_Dwell(t, math.inf, int(counts)))

    def release(self, t: float) -> None:
        """The focus may move from ``t`` on (a move was commanded, or its position is lost)."""
        if self._dwells and self._dwells[-1].t1 == math.inf:
            self._dwells[-1].t1 = t

    @property
    def settled_at(self) -> float:
        """Start of the latest stationary interval (there must be one)."""
        return self._dwells[-1].t0

    def counts_during(self, a: float, b: float) -> int | None:
        """The focus counts if the focus was stationary over all of ``[a, b]``, else None."""
        # The next move is issued exactly ``margin`` after a claimed exposure ends: compare with
        # a tolerance far below any timing that matters so rounding cannot lose that frame.
        margin = self._timing_margin_s - TIME_EPS_S
        for dwell in reversed(self._dwells):
            if dwell.t0 + margin <= a and b <= dwell.t1 - margin:
                return dwell.counts
            if dwell.t1 <= a:
                break
        return None


@dataclass(slots=True)
class _Dwell:
    """The focus was stationary at ``counts`` over ``[t0, t1)``."""

    t0: float
    t1: float
    counts: int
