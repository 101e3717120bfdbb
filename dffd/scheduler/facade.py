"""The scheduler facade: tags frames, decides focus and pan/tilt actions from events.

Pure and synchronous (docs/design.md §2.3, §5): no I/O, no clock of its own, no asyncio. The
daemon shell feeds it events stamped with monotonic times and executes the actions it returns;
the same object runs live, in virtual time, and in the unit tests.

Event-driven API (every ``t``/``now`` is in the frame source's monotonic seconds):

- ``on_frame(index, t) -> FrameTag``: a frame exposed around mid-time ``t`` was delivered; the
  tag says what the focus and pan/tilt were during the *whole* exposure ``[t − E/2, t + E/2]``:
  ``burst`` (a claimed slot), ``track`` (stationary known focus, normally the tracking focus),
  ``transit`` (the focus moved or may have, or the frame falls between a burst's slots).
- ``on_focus_completed(move_id, t)`` / ``on_focus_failed(move_id, t)``: VISCA Completion (or an
  error/timeout) for a :class:`FocusMove`.
- ``on_focus_position(t, counts)``: reply to a :class:`FocusInquiry`.
- ``on_pan_tilt_done(t)`` / ``on_pan_tilt_failed(t)`` / ``on_pan_tilt_position(t, pan, tilt)``.
- ``on_estimate(...)``: what the estimator thread learned from a frame (σ of ẑ, the next burst
  plan, the target's centroid) — drives the burst policy and the pan/tilt controller.
- ``next_actions(now) -> list[Action]`` then ``next_wakeup() -> float | None``: the shell calls
  ``next_actions`` after every event and at the wake-up time, and executes what it returns
  (focus actions on one VISCA socket, pan/tilt on the other — concurrently).

How a frame's focus is known: :mod:`dffd.scheduler.focus`; how bursts are timed, their modes
and policy: :mod:`dffd.scheduler.bursts`; the exposure clock: :mod:`dffd.scheduler.clock`;
pan/tilt: :mod:`dffd.scheduler.head`.

Acquisition and loss. The core's burst plans are ignored until the contour has been seen on
``acquire_stable_frames`` consecutive frames (acquire first, then bursts). Frames without a
contour for up to ``pan_tilt_lost_s`` are coasted through (transit blur, brief occlusion); after
that the target is lost and the head *searches*: it keeps driving along the target's predicted
path for ``pan_tilt_search_s`` (a target that left the field of view most likely did so along
its motion), then returns to the direction where the target was last seen with one absolute move
and holds there. The core re-searches the frame throughout, so a target that comes back into
view is re-acquired and followed again.

Why this module is past the ~600-line guideline: it is one state machine and nothing else. The
frame tagging, the focus and pan/tilt events, the estimator feedback, the burst and rolling-bracket
steps and the start-up holds of :class:`Scheduler` all read and write the same state (the phase,
the one focus move in flight, the known and the tracking focus, the plan and σ, the burst being
executed and its claims, the hold) and keep its invariants together (one focus move at a time,
settled by its Completion, its failure or a reading; a frame tagged ``burst`` only for a claimed
slot exposed whole at a known, stationary focus). Spreading its methods over modules (mixins, a
chain of base classes) would scatter those invariants over files; what is not the state machine,
its vocabulary and its parts (actions, config, stats, the exposure clock, the focus history, the
burst ledger, the pan/tilt head and its search sweep, the link budget), is already in the modules
named above and in :mod:`dffd.scheduler`.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import replace
from typing import Literal

from dffd.core.types import FrameTag
from dffd.scheduler.actions import Action, FocusInquiry, FocusMove, PanTiltInquiry
from dffd.scheduler.budget import focus_move_time_s
from dffd.scheduler.bursts import ROLLING_SLOT, Burst, BurstLedger, order_settings
from dffd.scheduler.clock import ExposureClock
from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.focus import FocusHistory, Move
from dffd.scheduler.head import PanTiltHead
from dffd.scheduler.search import SearchStatus
from dffd.scheduler.stats import SchedulerStats

Phase = Literal[
    "init", "track", "burst_wait", "burst_move", "burst_dwell", "return_move", "recover"
]

# Frames beyond the capture latency without a delivery before the capture counts as stalled.
STALL_FRAMES = 3
# Exposure times of recent transit tags: the estimator's feedback arrives a few frames late at
# most (capture latency + estimator queue), far fewer than this.
TRANSIT_HISTORY = 32
# Start-up holds at the end that closes a bracket once the core reports a depth (σ): the first
# depth of a far target is the second burst's (the first, full-range one lies outside its
# bracket and the daemon withholds it), and holding for it publishes it ~0.2 s sooner (lock-step,
# reference simulator, 8-11 m); later holds would cost the rolling triangle 2-3 frames each.
HOLDS_AFTER_DEPTH = 1


class Scheduler:
    """Decides focus and pan/tilt commands and tags frames; see the module docstring."""

    def __init__(self, config: SchedulerConfig) -> None:
        self.config = config
        self.stats = SchedulerStats()
        self._phase: Phase = "init"
        self._history = FocusHistory(config.timing_margin_s)
        self._move: Move | None = None
        self._next_move_id = 1
        self._burst: Burst | None = None  # the burst whose moves are being executed
        self._bursts = BurstLedger(self.stats)  # claims awaiting frames
        self._next_burst_id = 1
        # Focus knowledge.
        self._counts: int | None = None  # stationary counts, if known
        self._track_counts: int | None = config.initial_focus_counts
        self._acquire_counts: int | None = config.initial_focus_counts  # focus of a sweep
        self._track_from = -math.inf  # tracking exposures count from this time
        self._inquiry_due = 0.0
        self._inquiry_pending = False
        self._last_reading: int | None = None
        # Frame timing.
        self._clock = ExposureClock(config.period_s, config.exposure)
        self._last_tagged_mid = -math.inf
        # Estimator feedback.
        self._plan: tuple[int, ...] | None = None
        self._sigma: float | None = None
        self._burst_now = False
        self._stable = 0  # consecutive frames with a centroid (acquisition)
        self._centroid_t = -math.inf
        # Rolling bracket: the side of the next end (+1 high counts, −1 low).
        self._rolling_side = -1
        self._last_end_counts: int | None = None  # the last rolling end's focus
        # Start-up hold (see _hold_at_end): the lens stays at the end that closed the first
        # bracket until the core's feedback for a frame exposed after ``_hold_after`` arrived,
        # or until ``_hold_until`` (frames stopped coming).
        self._hold_after: float | None = None
        self._hold_until = -math.inf
        self._hold_ended = False  # a hold just ended: the next re-target may open a sequence
        self._hold_opens = False  # the hold was before any depth (then _hold_ended is set)
        # Holds since the core reported a depth (σ), reset while it reports none (start, loss).
        self._depth_holds = HOLDS_AFTER_DEPTH
        # The next rolling end opens a sequence in the core: the frames held at the last end are
        # its tracking frames, so no middle lies between that end and the next one.
        self._next_end_opens = False
        self._transit_ts: deque[float] = deque(maxlen=TRANSIT_HISTORY)
        # Pan/tilt.
        self._pt = PanTiltHead(config)

    # -- queries ----------------------------------------------------------------------------
    @property
    def phase(self) -> Phase:
        """Current phase of the focus state machine."""
        return self._phase

    @property
    def focus_counts(self) -> int | None:
        """Focus counts if the lens is known to be stationary now, else None."""
        return self._counts

    @property
    def track_counts(self) -> int | None:
        """The tracking (best) focus the scheduler returns to between bursts."""
        return self._track_counts

    @property
    def frame_period_s(self) -> float:
        """Frame period estimated from delivered timestamps."""
        return self._clock.period

    @property
    def searching(self) -> bool:
        """The target is lost and pan/tilt is searching along its predicted path."""
        return self._pt.searching

    def pan_tilt_at(self, t: float) -> tuple[float, float]:
        """Model pan/tilt (deg) at time ``t``."""
        return self._pt.at(t)

    def achieved_rate_hz(self, now: float, window_s: float = 10.0) -> float:
        """Completed bursts per second over the last ``window_s`` seconds."""
        return self._bursts.achieved_rate_hz(now, window_s)

    # -- frame events -----------------------------------------------------------------------
    def on_frame(self, index: int, t: float) -> FrameTag:
        """Tag the frame exposed around mid-time ``t`` (delivered now).

        ``track``: whole exposure at a known, stationary focus that is not a claimed burst slot
        (normally the tracking focus); ``burst``: a claimed slot; ``transit``: the focus moved (or
        may have moved, or was unknown) during the exposure.
        """
        self._clock.update(index, t)
        pan, tilt = self._pt.at(t)
        half = self.config.exposure / 2.0
        counts = self._history.counts_during(t - half, t + half)
        tag: FrameTag
        if counts is None:
            tag = FrameTag("transit", None, pan, tilt)
        else:
            slot = self._bursts.claim_for(t, counts, self._clock.period / 2.0)
            if slot is not None:
                tag = FrameTag("burst", counts, pan, tilt, slot)
            elif self._bursts.inside_burst(t, self._clock.period / 2.0):
                # An unclaimed frame between a burst's slots (exposed whole at a burst setting):
                # a ``track`` tag would end the burst early in the core, so centroid only.
                tag = FrameTag("transit", None, pan, tilt)
            else:
                tag = FrameTag("track", counts, pan, tilt)
        if tag.role == "track":
            self._bursts.track_since_end = True
        elif tag.role == "transit":
            self._transit_ts.append(t)
        self._drop_missed_claims(t)
        self._last_tagged_mid = max(self._last_tagged_mid, t)
        self.stats.frames[tag.role] += 1
        return tag

    # -- focus events -----------------------------------------------------------------------
    def on_focus_completed(self, move_id: int, t: float) -> None:
        """Completion of :class:`FocusMove` ``move_id`` received at ``t``."""
        if self._move is None or self._move.move_id != move_id:
            return  # late or duplicate Completion: the move was already resolved
        self._settle(self._move.target, t)

    def on_focus_failed(self, move_id: int, t: float) -> None:
        """The move failed or timed out: the focus position is uncertain until inquired."""
        if self._move is None or self._move.move_id != move_id:
            return
        self.stats.focus_failures += 1
        self._enter_recover(t)

    def on_focus_position(self, t: float, counts: int) -> None:
        """Reply to a :class:`FocusInquiry` received at ``t``.

        Settles the focus when the reading equals the outstanding move's target, or (with no
        move outstanding) when two consecutive readings agree.
        """
        self._inquiry_pending = False
        tol = self.config.focus_tolerance_counts
        if self._move is not None:
            if abs(counts - self._move.target) <= tol:
                self._settle(counts, t)
            return
        if self._phase != "recover":
            return
        if self._last_reading is not None and abs(counts - self._last_reading) <= tol:
            self._settle(counts, t)
        else:
            self._last_reading = counts
            self._inquiry_due = t + self.config.focus_inquiry_interval_s

    def on_focus_inquiry_failed(self, t: float) -> None:
        """A :class:`FocusInquiry` got no valid reply; it is retried later."""
        self._inquiry_pending = False
        self._inquiry_due = t + self.config.focus_inquiry_interval_s

    def invalidate_focus(self, t: float) -> None:
        """Forget what the focus is (e.g. the link was reset); re-learn it by inquiry."""
        self._enter_recover(t)

    # -- pan/tilt events --------------------------------------------------------------------
    def on_pan_tilt_done(self, t: float) -> None:
        """The last pan/tilt action finished (Completion received or inquiry answered)."""
        self._pt.on_done(t)

    def on_pan_tilt_failed(self, t: float) -> None:
        """The last pan/tilt action failed; the model is re-anchored by the next inquiry."""
        self._pt.on_done(t)
        self._pt.poll_due = t
        self.stats.pan_tilt_failures += 1

    def on_pan_tilt_position(self, t: float, pan_deg: float, tilt_deg: float) -> None:
        """Pan/tilt position reply received at ``t`` (also ends the inquiry)."""
        self._pt.anchor(t, pan_deg, tilt_deg)

    # -- estimator feedback -----------------------------------------------------------------
    def on_estimate(
        self,
        t: float,
        *,
        sigma_m: float | None,
        plan: tuple[int, ...] | None,
        centroid_px: tuple[float, float] | None,
        pan_deg: float | None = None,
        tilt_deg: float | None = None,
        track_rate_deg_s: tuple[float, float] | None = None,
    ) -> None:
        """Feedback from the core for the frame exposed at ``t``.

        ``plan``: the next burst's settings (``Pipeline.plan_burst``), None while the core has no
        depth to bracket (no bursts then). ``centroid_px``: the target's image centroid, None when
        lost (pan/tilt stops). ``pan_deg``/``tilt_deg``: the tag's pan/tilt for that exposure.
        ``track_rate_deg_s``: the 3D tracker's pan/tilt rate of the target's direction at ``t``
        (feed-forward when ``pan_tilt_track_feedforward``), None without a track.
        """
        if track_rate_deg_s is not None:
            self._pt.on_track_rate(t, track_rate_deg_s)
        if self._hold_after is not None and t > self._hold_after:
            self._hold_after = None  # the frame exposed at the held end has been processed
            self._hold_ended = self._hold_opens
        if sigma_m is None:
            self._depth_holds = 0
        self._sigma = sigma_m
        need = self.config.acquire_stable_frames
        if centroid_px is not None:
            self._stable += 1
            self._centroid_t = t
        elif self._stable < need or t - self._centroid_t > self.config.pan_tilt_lost_s:
            self._stable = 0  # not acquired yet, or lost: acquire again before bursts
        if self._stable < need:
            plan = None  # acquire first: no bursts until the contour has been stable a while
        elif plan is None and centroid_px is not None and t in self._transit_ts:
            # The core plans from a known focus: a transit frame of a tracked target has no plan
            # of its own, which must not cancel the last one (else the rolling bracket waits for
            # the next tracking frame's plan; docs/estimation.md §6.1).
            plan = self._plan
        if plan is not None:
            self._plan = tuple(sorted(int(c) for c in plan))
            self._track_counts = self._plan[len(self._plan) // 2]
        else:
            self._plan = None
        self._feedback_pan_tilt(t, sigma_m, centroid_px, pan_deg, tilt_deg)

    def _feedback_pan_tilt(
        self,
        t: float,
        sigma_m: float | None,
        centroid_px: tuple[float, float] | None,
        pan_deg: float | None,
        tilt_deg: float | None,
    ) -> None:
        limit = self.config.sigma_trigger_m
        if limit is not None and sigma_m is not None and sigma_m > limit:
            self._burst_now = True
        if pan_deg is None or tilt_deg is None:
            pan_deg, tilt_deg = self._pt.at(t)
        self._pt.on_centroid(t, centroid_px, pan_deg, tilt_deg)

    def set_track_focus(self, counts: int) -> None:
        """Tracking focus to use until the core plans bursts (e.g. from an initial depth); the
        first one given is also the focus of a search sweep (the acquisition focus)."""
        self._track_counts = int(counts)
        if self._acquire_counts is None:
            self._acquire_counts = int(counts)

    def set_policy(self, every_frames: int, sigma_trigger_m: float | None) -> None:
        """Change the burst policy at run time (the ``set_burst_policy`` command)."""
        self.config = replace(
            self.config, burst_every_frames=every_frames, sigma_trigger_m=sigma_trigger_m
        )

    def request_burst(self) -> None:
        """Start a burst at the next opportunity (if a plan exists)."""
        self._burst_now = True

    def cancel_bursts(self) -> None:
        """Forget the plan (target released): no new bursts until a new plan arrives."""
        self._plan = None
        self._burst_now = False

    def stop_pan_tilt(self) -> None:
        """Stop following the target: one stop is issued, then nothing until a new centroid;
        no search sweep until :meth:`arm_search` (``release``)."""
        self._pt.release()

    def arm_search(self, t: float) -> None:
        """Automatic acquisition from ``t`` (``acquire`` without an ROI, a start without one):
        when no target is seen for ``search_after_s`` the head sweeps its range
        (:mod:`dffd.scheduler.search`); a sighting ends the sweep, a loss re-arms it."""
        self._pt.arm_search(t)

    def disarm_search(self) -> None:
        """Acquisition in an ROI: no sweep until the target has been seen (then a loss sweeps)."""
        self._pt.search.disarm(until_seen=True)

    @property
    def search_armed(self) -> bool:
        """Automatic acquisition is in force (a sweep follows when nothing is seen)."""
        return self._pt.search.armed

    @property
    def search_status(self) -> SearchStatus | None:
        """The search sweep while no target is followed (None: not armed, or following one)."""
        return self._pt.search_status()

    # -- decisions --------------------------------------------------------------------------
    def next_actions(self, now: float) -> list[Action]:
        """Actions due at ``now``; the shell executes them in order (focus first)."""
        actions: list[Action] = []
        if self._pt.search.sweeping and self._plan is None and self._acquire_counts is not None:
            # The target's depth is unknown again: look at the acquisition focus.
            self._track_counts = self._acquire_counts
        focus_action = self._focus_step(now)
        if focus_action is not None:
            actions.append(focus_action)
            if isinstance(focus_action, FocusMove):
                self._pt.focus_command_at(now)
        pt = self._pt.step(now, self._next_focus_command_time(now), self._quiet_at(now))
        if pt is not None:
            actions.append(pt)
            if not isinstance(pt, PanTiltInquiry):
                self.stats.pan_tilt_commands += 1
        return actions

    def next_wakeup(self) -> float | None:
        """When ``next_actions`` must be called again (None: only on the next event)."""
        times: list[float] = []
        pt = self._pt.wakeup(self._next_focus_command_time(None))
        if pt is not None:
            times.append(pt)
        if self._phase == "recover" and not self._inquiry_pending:
            times.append(self._inquiry_due)
        nxt = self._focus_wakeup()
        if nxt is not None:
            times.append(nxt)
        return min(times) if times else None

    def _quiet_at(self, now: float) -> float | None:
        """Start of the next exposure the core measures on (burst/track at a stationary focus):
        ``now`` or earlier while the focus is stationary, the first exposure after the predicted
        Completion while a move runs (the focus transit is the pan/tilt's free window), None while
        no bursts run (acquisition, recovery: no exposure to keep free of head corrections)."""
        if self._plan is None or self._clock.t_ref is None or self._phase in ("init", "recover"):
            return None
        move = self._move
        if move is None:
            return now
        if move.t_done == math.inf:
            return now  # unknown travel: assume it ends at once (no correction in its shadow)
        mid = self._clock.first_mid_starting_after(move.t_done + self.config.guard_s)
        return mid - self.config.exposure / 2.0

    # -- internals: focus state machine -----------------------------------------------------
    def _focus_step(self, now: float) -> Action | None:
        if self._phase == "recover":
            if not self._inquiry_pending and now >= self._inquiry_due:
                self._inquiry_pending = True
                self.stats.focus_inquiries += 1
                return FocusInquiry()
            return None
        if self._move is not None:
            return None
        if self._phase == "init":
            if self._track_counts is not None:
                return self._issue_move(self._track_counts, now, "return_move")
            self._enter_recover(now)
            return self._focus_step(now)
        if self._phase == "track":
            assert self._counts is not None
            if self._holding(now):
                return None
            after_hold, self._hold_ended = self._hold_ended, False
            home = self._track_counts
            if home is not None and abs(home - self._counts) > self._retarget_threshold():
                if self._opens_rolling_here(now, after_hold=after_hold):
                    # Before the first depth, or on the first bracket's new plan after a hold:
                    # open a sequence at an end of the plan instead of going to the middle
                    # first (saves a middle dwell and the travel to the middle; no bracket made
                    # of two plans).
                    return self._open_rolling(now)
                # The best focus drifted away from the lens: re-focus the tracking frames.
                return self._issue_move(home, now, "return_move")
            if self._should_burst(now):
                return self._start_burst(now)
            return None
        if self._phase == "burst_wait":
            burst = self._burst
            assert burst is not None
            if now < burst.start_at:
                return None
            if burst.rolling and self._plan is not None:
                # The end's counts are fixed only now, from the latest plan: the claimed frame is
                # a tracking frame, and the plan of the frame before it (delivered by now) carries
                # the burst the core fitted there (committing at the claim would use a plan one
                # burst older; docs/estimation.md §6.1).
                if not burst.opening and self._plan_left_the_lens():
                    return self._retarget_rolling(burst, now)
                burst.order = (self._plan[-1] if burst.side > 0 else self._plan[0],)
                self._last_end_counts = burst.order[0]
            if burst.order[0] == self._counts:
                # The lens is there already (a sequence opened where a start-up hold left it).
                self._claim_after(now)
                return None
            return self._issue_move(burst.order[0], now, "burst_move")
        if self._phase == "burst_dwell":
            burst = self._burst
            assert burst is not None
            if now < self._clock.end_of(burst.claims[burst.slot]) + self.config.guard_s:
                return None
            return self._advance_burst(now)
        return None

    def _focus_wakeup(self) -> float | None:
        """When the focus machine must be looked at again (None: on the next event)."""
        if self._phase == "track" and self._move is None and self._hold_after is not None:
            return self._hold_until
        if self._phase == "track" and self._move is None:
            commit = self._burst_commit_time(None)
            if commit is not None and self._frames_flowing(commit):
                return commit
            return None
        return self._next_focus_command_time(None)

    def _next_focus_command_time(self, now: float | None) -> float | None:
        """When the focus machine next wants the link (for wake-ups and link budgeting)."""
        if self._move is not None or self._phase == "recover":
            return None
        margin = self.config.guard_s
        if self._phase == "burst_dwell" and self._burst is not None:
            return self._clock.end_of(self._burst.claims[self._burst.slot]) + margin
        if self._phase == "burst_wait" and self._burst is not None:
            return self._burst.start_at
        if self._phase == "track" and self._plan is not None and self._clock.t_ref is not None:
            claim = self._track_claim_mid(now)
            if claim is not None:
                due = self._clock.end_of(claim) + margin
                # A stalled capture: nothing to wait for until the next frame arrives.
                return due if self._frames_flowing(due) else None
        return None

    def _plan_step(self) -> int:
        """Smallest gap between the planned settings (0 without a plan)."""
        plan = self._plan
        if plan is None or len(plan) < 2:
            return 0
        return min(b - a for a, b in itertools.pairwise(plan))

    def _snap_threshold(self) -> float:
        return max(float(self.config.snap_counts), self.config.snap_fraction * self._plan_step())

    def _retarget_threshold(self) -> float:
        return max(float(self.config.snap_counts), self.config.retarget_steps * self._plan_step())

    def _should_burst(self, now: float) -> bool:
        if self._clock.t_ref is None or not self._frames_flowing(now):
            return False
        commit = self._burst_commit_time(now)
        return commit is not None and now >= commit

    def _burst_commit_time(self, now: float | None) -> float | None:
        """When the next burst is committed: the start of its first claimed exposure.

        Committing before that exposure can have been delivered (even with zero capture latency)
        lets the frame be tagged ``burst`` on arrival; its settings are fixed from then on.
        """
        if self._plan is None:
            return None
        claim = self._track_claim_mid(now)
        return None if claim is None else claim - self.config.exposure / 2.0

    def _frames_flowing(self, now: float) -> bool:
        """A frame was delivered recently (claims on a stalled capture would be wasted)."""
        assert self._clock.t_ref is not None
        cfg = self.config
        expected_age = (
            cfg.capture_latency_frames + STALL_FRAMES
        ) * self._clock.period + cfg.exposure
        return now - self._clock.t_ref <= expected_age

    def _track_claim_mid(self, now: float | None) -> float | None:
        """Mid-time of the tracking exposure that becomes the next burst's first slot."""
        if self._counts is None or self._clock.t_ref is None:
            return None
        first = self._clock.first_mid_starting_after(self._track_from)
        eligible = max(first, self._clock.next_mid_after(self._last_tagged_mid))
        if self._burst_now:
            if now is None:
                return eligible
            latest = self._clock.last_mid_ending_before(now - self.config.guard_s)
            return max(eligible, latest)
        every = self.config.burst_every_frames
        if self.config.burst_mode == "rolling":
            # The claimed exposure is the last of the tracking frames at the middle. Before the
            # first depth the plan does not change from frame to frame (it spans the working
            # range): one frame at the middle.
            every = 0 if self._sigma is None else max(1, every) - 1
        return max(eligible, first + every * self._clock.period)

    def _start_burst(self, now: float) -> Action | None:
        assert self._plan is not None
        assert self._counts is not None
        claim_mid = self._track_claim_mid(now)
        current = self._counts
        if self.config.burst_mode == "rolling":
            # One end per burst, alternating sides: with the previous end and the middle frame
            # between them it makes three settings (the core assembles them).
            end = self._plan[-1] if self._rolling_side > 0 else self._plan[0]
            self._rolling_side = -self._rolling_side
            order: tuple[int, ...] = (end,)
            burst = Burst(
                self._next_burst_id, order, tag_slots=(ROLLING_SLOT,), rolling=True,
                side=-self._rolling_side, opening=self._next_end_opens,
            )  # fmt: skip
            self._next_end_opens = False
        else:
            settings = list(self._plan)
            # Take a planned setting where the lens already is (the tag carries the real counts).
            nearest = min(range(len(settings)), key=lambda i: abs(settings[i] - current))
            if abs(settings[nearest] - current) <= self._snap_threshold():
                settings[nearest] = current
            home = self._track_counts if self._track_counts is not None else current
            order = order_settings(current, tuple(settings), home, self.config)
            burst = Burst(self._next_burst_id, order)
        self._next_burst_id += 1
        self._burst = burst
        self._bursts.pending.append(burst)
        self._burst_now = False
        self.stats.bursts_started += 1
        assert claim_mid is not None
        if order[0] == current:
            # Slot 0 is the tracking-focus exposure being committed: the lens is already there.
            burst.claims.append(claim_mid)
            burst.tagged.append(False)
            self._phase = "burst_dwell"
        else:
            # That exposure stays a tracking frame; the first move follows it.
            burst.start_at = self._clock.end_of(claim_mid) + self.config.guard_s
            self._phase = "burst_wait"
        return self._focus_step(now)

    def _opens_rolling_here(self, now: float, *, after_hold: bool = False) -> bool:
        """Rolling, a plan but no depth yet (σ unknown: a burst is due at once) or the first plan
        after a start-up hold (:meth:`_hold_at_end`) whose bracket left the lens, frames flowing.

        Then a re-target opens a new sequence at the plan's end nearest the lens. Going to the
        middle first would make the next end close a burst with the previous end, of the older
        plan: after the first, full-range burst that bracket spans two plans; on the demo it was
        dropped (no cost at the far end) or fitted 1.3-4.7 m off for a target at 10 m, and the
        first depth waited for one more end.
        """
        if self.config.burst_mode != "rolling" or self._plan is None:
            return False
        if self._sigma is not None and not (after_hold and self._plan_left_the_lens()):
            return False
        return self._clock.t_ref is not None and self._frames_flowing(now)

    def _open_rolling(self, now: float) -> Action | None:
        """Move straight to an end of the plan: the end that opens a sequence.

        Before the first depth, the near end, so that the bracket ends at its far end: the
        full-range first bracket's vertex falls outside it for targets near its ends (on the
        reference simulator, lock-step: 1.8, 3 and 5 m inside; 1.5, 8, 10 and 11 m outside), in
        depth mostly at the far end, and the next bracket is then near the far end, where the
        lens already is. Otherwise (and when the lens already sits at an end) the end nearest
        the lens.
        """
        assert self._plan is not None
        assert self._counts is not None
        lo, hi = self._plan[0], self._plan[-1]
        if self._sigma is None and not self._at_plan_end():
            # No depth yet: the first bracket spans the working range; it ends at its far end.
            side = -self.config.far_focus_side
        else:
            side = 1 if abs(hi - self._counts) < abs(lo - self._counts) else -1
        self._rolling_side = -side  # the next burst takes the other end
        burst = Burst(
            self._next_burst_id, (hi if side > 0 else lo,), tag_slots=(ROLLING_SLOT,),
            rolling=True, side=side, start_at=now, opening=True,
        )  # fmt: skip
        self._next_burst_id += 1
        self._next_end_opens = False
        self._burst = burst
        self._bursts.pending.append(burst)
        self._burst_now = False
        self.stats.bursts_started += 1
        self._phase = "burst_wait"
        return self._focus_step(now)

    def _at_plan_end(self) -> bool:
        """The lens sits at one of the plan's ends (within the snap threshold)."""
        assert self._plan is not None
        assert self._counts is not None
        near = self._snap_threshold()
        return min(abs(self._plan[0] - self._counts), abs(self._plan[-1] - self._counts)) <= near

    def _plan_left_the_lens(self) -> bool:
        """The plan's bracket no longer contains the lens (where the middle frames were taken):
        an end of this plan would make a bracket of two plans. (A plan that drifts with the
        target, as in steady tracking, keeps the lens inside its bracket.)"""
        plan = self._plan
        assert plan is not None
        assert self._counts is not None
        return not plan[0] <= self._counts <= plan[-1]

    def _retarget_rolling(self, burst: Burst, now: float) -> Action | None:
        """Drop the end not yet moved to, re-focus the middle; the next end opens a sequence.

        Measured on the demo (target at 10 m, first bracket over the working range): the lens
        went from the old middle straight to the new plan's far end, and the core closed a
        burst of the old plan's end, the old middle and that end — dropped ("depth jump") or
        fitted 1.8-3.3 m off, and published as the first depth. The next end is taken on the same
        side of the new middle as the last end, so the core opens a sequence with it.
        """
        if burst in self._bursts.pending:
            self._bursts.pending.remove(burst)
        self.stats.bursts_started -= 1  # never started: no move, no claim
        self._burst = None
        assert self._track_counts is not None
        last = self._last_end_counts
        if last is not None:
            self._rolling_side = 1 if last > self._track_counts else -1
        return self._issue_move(self._track_counts, now, "return_move")

    def _advance_burst(self, now: float) -> Action | None:
        burst = self._burst
        assert burst is not None
        burst.slot += 1
        if burst.slot < len(burst.order):
            target = burst.order[burst.slot]
            if target == self._counts:
                self._claim_after(now)
                return None
            return self._issue_move(target, now, "burst_move")
        # All slots claimed: back to the tracking focus (the latest plan's centre).
        self._burst = None
        if self._hold_at_end(burst):
            return None
        home = self._track_counts if self._track_counts is not None else burst.order[-1]
        assert self._counts is not None
        if abs(home - self._counts) <= self.config.focus_tolerance_counts:
            self._phase = "track"
            self._track_from = self._clock.end_of(burst.claims[-1])
            return None
        return self._issue_move(home, now, "return_move")

    def _hold_at_end(self, burst: Burst) -> bool:
        """At start-up, stay at the rolling end that closes a bracket (True).

        The core closes a burst at the next tracking frame wherever the lens is. Before the
        first depth the bracket's middle is only the old plan's (the first bracket spans the
        working range), and the first burst re-plans the bracket: a frame held at the end closes
        it within a frame or two instead of a half-bracket move back to the middle, and the lens
        goes from the end straight to the new plan once the core's feedback on that frame is in.
        The first closing end after the first depth is held too (``HOLDS_AFTER_DEPTH``): a far
        target's first published depth is that burst's. The core does not take the held frames'
        sizes for a depth jump (they are defocused:
        ``dffd.core.pipeline_config.SIZE_JUMP_MAX_BLUR_PX``).
        """
        if not burst.rolling or burst.opening or not burst.claims:
            return False
        if self._sigma is not None:
            if self._depth_holds >= HOLDS_AFTER_DEPTH:
                return False
            self._depth_holds += 1
        self._hold_opens = self._sigma is None
        self._next_end_opens = True
        cfg = self.config
        period = self._clock.period
        self._phase = "track"
        self._track_from = self._clock.end_of(burst.claims[-1])
        # The first frame exposed after the end's (its mid-time past the end's by half a period,
        # whatever the timestamp jitter) carries the core's new plan.
        self._hold_after = burst.claims[-1] + period / 2.0
        self._hold_until = (
            self._track_from + (cfg.capture_latency_frames + STALL_FRAMES + 1) * period
        )
        return True

    def _holding(self, now: float) -> bool:
        """A start-up hold is waiting for the core's feedback (see :meth:`_hold_at_end`)."""
        if self._hold_after is None:
            return False
        if now >= self._hold_until:
            self._hold_after = None  # no feedback in time (frames stopped): go on without it
            self._hold_ended = self._hold_opens
            return False
        return True

    def _claim_after(self, t: float) -> None:
        """Claim the first exposure starting after ``t`` (+margin) for the current slot."""
        burst = self._burst
        assert burst is not None
        start = t + self.config.guard_s
        mid = (
            self._clock.first_mid_starting_after(start) if self._clock.t_ref is not None else start
        )
        mid = max(mid, self._clock.next_mid_after(self._last_tagged_mid))
        burst.claims.append(mid)
        burst.tagged.append(False)
        self._phase = "burst_dwell"

    def _issue_move(self, target: int, now: float, phase: Phase) -> FocusMove:
        move = Move(self._next_move_id, int(target), now)
        if self._counts is not None:
            move.t_done = now + focus_move_time_s(self.config, int(target) - self._counts)
        self._next_move_id += 1
        self._move = move
        self._phase = phase
        self._history.release(now)  # the lens may move from the moment it is commanded
        self._counts = None
        self.stats.focus_moves += 1
        return FocusMove(move.move_id, move.target)

    def _settle(self, counts: int, t: float) -> None:
        phase = self._phase
        self._move = None
        self._counts = int(counts)
        self._last_reading = None
        self._inquiry_pending = False
        self._history.settle(t, counts)
        if phase == "burst_move" and self._burst is not None:
            self._claim_after(t)
        else:
            self._phase = "track"
            self._track_from = t + self.config.guard_s

    def _enter_recover(self, t: float) -> None:
        self._history.release(t)
        self._move = None
        self._counts = None
        self._phase = "recover"
        self._last_reading = None
        self._inquiry_pending = False
        self._inquiry_due = t
        if self._burst is not None:
            self._fail(self._burst)

    def _fail(self, burst: Burst) -> None:
        """A burst cannot complete: forget its claims (its frames are tagged ``track``)."""
        if burst in self._bursts.pending:
            self._bursts.pending.remove(burst)
            self.stats.bursts_incomplete += 1
        if burst.rolling:
            self._bursts.rolling_end_t = None  # the core lacks that end: the next one opens anew
        if burst is self._burst:
            self._burst = None
            if self._phase in ("burst_dwell", "burst_wait"):
                self._phase = "track"
                self._track_from = -math.inf if self._counts is None else self._history.settled_at
            elif self._phase == "burst_move":
                self._phase = "return_move"

    # -- internals: claims ------------------------------------------------------------------
    def _drop_missed_claims(self, t: float) -> None:
        tol = self._clock.period / 2.0
        for burst in list(self._bursts.pending):
            if burst.missed(t, tol):
                self._fail(burst)
