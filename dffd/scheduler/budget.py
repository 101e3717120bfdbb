"""Link budget: how long focus moves take, and the depth rate an ideal scheduler reaches."""

from __future__ import annotations

import math
from dataclasses import dataclass

from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.wire import COMPLETION_BYTES, FOCUS_DIRECT_BYTES, link_time_s


@dataclass(frozen=True, slots=True)
class RateLimit:
    """The depth-measurement rate an ideal scheduler reaches with this configuration."""

    depth_hz: float
    cycle_frames: int  # frame periods per measurement cycle (bursts + tracking)
    move_frames: tuple[int, ...]  # frame periods each focus move of a burst costs
    move_s: tuple[float, ...]  # command → Completion time of each move
    predictive: bool


def focus_move_time_s(config: SchedulerConfig, delta_counts: int) -> float:
    """Command written → Completion received, for a focus move of ``delta_counts``."""
    if delta_counts == 0:
        return 0.0
    return (
        link_time_s(FOCUS_DIRECT_BYTES, config.baudrate)
        + config.command_slot_s
        + abs(delta_counts) / config.focus_speed_counts_per_s
        + link_time_s(COMPLETION_BYTES, config.baudrate)
    )


def depth_rate_limit(
    config: SchedulerConfig, spacing_counts: int | tuple[int, int], *, predictive: bool = True
) -> RateLimit:
    """Theoretical depth measurements per second for brackets ``c−s, c, c+s`` (docs/design.md §5.5).

    ``spacing_counts``: the half-span ``s``, or the bracket's two sides ``(c − lo, hi − c)``: the
    core's brackets are symmetric in ``v``, not in counts (the lens table is not linear), and a
    side a few hundred counts longer can need one frame period more than the other (measured:
    2774 and 3150 counts on the reference lens at 30 fps, 6 and 7 periods).

    A move issued when a claimed exposure ends (+margin) and completed ``t_move`` later makes the
    next usable exposure ``ceil((E + 2·guard + t_move)/T)`` periods after the claimed one. Without
    prediction the move waits for the claimed frame to be delivered: the capture latency adds to
    every move.

    ``classic``: one cycle is the burst's slot at the tracking focus, a move of ``s`` to one side,
    ``2s`` to the other, ``s`` back, then ``burst_every_frames`` tracking frames.
    ``rolling``: one cycle is a move of ``s`` from the middle to an end (its frame closes a
    burst) and ``s`` back, plus the tracking frames at the middle beyond the first
    (``max(1, burst_every_frames) − 1``): a depth every two half-bracket moves.
    """
    if isinstance(spacing_counts, tuple):
        low, high = abs(int(spacing_counts[0])), abs(int(spacing_counts[1]))
    else:
        low = high = abs(int(spacing_counts))
    period = config.period_s
    wait = config.exposure + 2.0 * config.guard_s
    if not predictive:
        wait += config.capture_latency_frames * period
    rolling = config.burst_mode == "rolling"
    spaced = low > 0 or high > 0
    if rolling:
        # Alternate cycles go to either end and back: on average one move of each side.
        moves: tuple[int, ...] = (low, high) if spaced else ()
    else:
        moves = (low, low + high, high) if spaced else ()
    move_s = tuple(focus_move_time_s(config, d) for d in moves)
    move_frames = tuple(max(1, math.ceil((wait + t) / period - 1e-9)) for t in move_s)
    if rolling:
        # A zero spacing still takes the end's frame and a middle frame (two periods).
        cycle = sum(move_frames) + max(1, config.burst_every_frames) - 1 + (0 if moves else 2)
    else:
        # A zero spacing means three frames at one setting (degenerate but well defined).
        cycle = sum(move_frames) + config.burst_every_frames + (0 if moves else 3)
    return RateLimit(
        depth_hz=config.fps / cycle,
        cycle_frames=cycle,
        move_frames=move_frames,
        move_s=move_s,
        predictive=predictive,
    )
