"""Bursts: their planning (slot order) and the ledger of claimed exposures awaiting frames.

How bursts are timed. Exposures are periodic; from the last delivered frame's timestamp and the
period the scheduler predicts the exposure windows of frames still in flight (capture latency)
and of future frames. For each burst slot it *claims* the first exposure that starts after the
focus settled, and issues the next move as soon as that exposure has *ended* — it does not wait
for the frame to be delivered, so the capture latency costs nothing in steady state. The claimed
frame is tagged ``burst`` with ``(burst id, slot)`` when it arrives; a claimed frame that never
arrives (dropped by the capture) leaves the burst incomplete (counted in
:class:`~dffd.scheduler.stats.SchedulerStats`).

Burst modes. ``rolling`` (the daemon's default): the focus runs a triangle lo, mid, hi, mid, lo, …
over the core's plan; ``max(1, burst_every_frames)`` tracking frames at the middle (the best focus,
so they are the tracking frames), then one exposure at the next end, alternating sides. Each end is
tagged ``burst`` with ``(id, 2)`` alone: it closes a burst with the previous end and the middle
frame between them (the core assembles it), so a depth comes every two half-bracket moves instead
of four plus the tracking frames. An end's counts are taken from the latest plan when its move is
issued (that plan carries the burst the core fitted at the frame before). The depth rates of
both modes are measured in docs/estimation.md §6. ``classic``: three settings per burst,
mid → end → end → mid.

Burst policy: one burst after ``burst_every_frames`` tracking exposures at the tracking focus, or
earlier when the reported σ of ẑ exceeds ``sigma_trigger_m``. Slot order minimises motor travel
(including the return to the tracking focus); a planned setting within ``snap_fraction`` of the
plan's step (or ``snap_counts``) of the current focus is taken where the lens already is (the core
fits over the real counts in the tag). Between bursts the lens is re-focused only when the plan's
centre has moved by more than ``retarget_steps`` bracket steps: chasing estimate noise with focus
moves would cost transit frames and restart the tracking count.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field

from dffd.scheduler.budget import focus_move_time_s
from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.stats import SchedulerStats

# Burst completion times kept for the achieved-rate estimate.
RATE_WINDOW = 64
# Slot number in the tag of a rolling burst's end frame: it closes a burst whose slots 0 and 1 are
# the previous end (the other side of the bracket) and the tracking frame at the middle between.
ROLLING_SLOT = 2
# A rolling end closes a burst only if the previous end was this recent (s); an older one (a
# recovery, a loss, a policy pause in between) opens a new sequence instead.
ROLLING_MAX_SPAN_S = 2.0
# Bursts whose claimed frames are still in flight (capture latency): a few at most.
PENDING_BURSTS = 8


@dataclass(slots=True)
class Burst:
    """One burst: its settings in order, and the exposure claimed for each slot so far."""

    burst_id: int
    order: tuple[int, ...]
    slot: int = 0  # the slot being acquired
    claims: list[float] = field(default_factory=list)  # predicted exposure mid-time per slot
    tagged: list[bool] = field(default_factory=list)
    start_at: float = -math.inf  # first move not before (the last tracking exposure's end)
    tag_slots: tuple[int, ...] = ()  # slot numbers in the tags (default: 0, 1, 2, …)
    rolling: bool = False
    side: int = 0  # rolling: +1 the plan's high end, −1 its low end
    opening: bool = False  # rolling: taken away from the middle on purpose (opens a sequence)

    def missed(self, t: float, tol: float) -> bool:
        """A claimed exposure of this burst is over (``t`` past it by ``tol``) but not tagged."""
        return any(
            not done and t >= mid + tol for mid, done in zip(self.claims, self.tagged, strict=True)
        )


def order_settings(
    current: int | None,
    settings: tuple[int, ...],
    home: int,
    config: SchedulerConfig,
) -> tuple[int, ...]:
    """Order burst settings to minimise the time of all moves, including the return ``home``."""

    def cost(order: tuple[int, ...]) -> tuple[float, int]:
        total = 0.0
        here = current
        for target in (*order, home):
            if here is None or here != target:
                delta = abs(target - here) if here is not None else abs(target - home)
                total += focus_move_time_s(config, max(1, delta))
            here = target
        # Tie-break: prefer starting where the lens already is (the first claim costs no move).
        return total, 0 if order and order[0] == current else 1

    return min(itertools.permutations(settings), key=cost)


class BurstLedger:
    """Bursts whose claimed exposures are awaiting their frames, and what completed."""

    def __init__(self, stats: SchedulerStats) -> None:
        self.pending: deque[Burst] = deque(maxlen=PENDING_BURSTS)
        self.completed_times: deque[float] = deque(maxlen=RATE_WINDOW)
        # Rolling bracket: when the last end was tagged, and whether a tracking frame (the
        # middle) was tagged since.
        self.rolling_end_t: float | None = None
        self.track_since_end = False
        self._stats = stats

    def achieved_rate_hz(self, now: float, window_s: float) -> float:
        """Completed bursts per second over the last ``window_s`` seconds."""
        recent = [t for t in self.completed_times if now - t <= window_s]
        if len(recent) < 2:
            return 0.0
        span = recent[-1] - recent[0]
        return (len(recent) - 1) / span if span > 0 else 0.0

    def claim_for(self, t: float, counts: int, tol: float) -> tuple[int, int] | None:
        """``(burst id, tag slot)`` of the claim the frame at ``t`` (focus ``counts``) fills."""
        for burst in self.pending:
            for slot, mid in enumerate(burst.claims):
                if burst.tagged[slot] or abs(t - mid) >= tol or counts != burst.order[slot]:
                    continue
                burst.tagged[slot] = True
                if len(burst.claims) == len(burst.order) and all(burst.tagged):
                    self.pending.remove(burst)
                    if not burst.rolling or self._closes_rolling(t):
                        self._stats.bursts_completed += 1
                        self.completed_times.append(t)
                    else:
                        self._stats.rolling_openings += 1
                tag_slot = burst.tag_slots[slot] if burst.tag_slots else slot
                return (burst.burst_id, tag_slot)
        return None

    def inside_burst(self, t: float, tol: float) -> bool:
        """``t`` lies after a burst's first claimed exposure and before its last one."""
        for burst in self.pending:
            if not burst.claims or t <= burst.claims[0] + tol:
                continue
            complete = len(burst.claims) == len(burst.order)
            if not complete or t < burst.claims[-1] - tol:
                return True
        return False

    def _closes_rolling(self, t: float) -> bool:
        """A rolling end tagged at ``t`` closes a burst (a recent previous end, a middle frame
        between); either way it becomes the previous end of the next one."""
        prev = self.rolling_end_t
        closes = prev is not None and t - prev <= ROLLING_MAX_SPAN_S and self.track_since_end
        self.rolling_end_t = t
        self.track_since_end = False
        return closes
