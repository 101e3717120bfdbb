"""Pan/tilt head model (dead reckoning between inquiries) and the target-centring controller.

In drive mode the VISCA speed table is coarse (2.0°/s is the
slowest: 0.2° = 22 px at f = 31 mm in one 0.1 s command interval), so a proportional controller
on it hunts around a slow target and smears the measured exposures. Instead each axis runs a
*quiet* speed code — the one nearest the target's filtered angular velocity (feed-forward from its
first two centroids on), 0 included, with hysteresis — through every exposure the core measures
on, and corrects its position with drive pulses in the *free windows* while the focus is in
transit (those frames are centroid-only): a correction starts when the error projected to the
window's end exceeds the band (``pan_tilt_deadband_deg``) and ends on time to be back on the quiet
code before the next measured exposure. Commands are issued at most every
``pan_tilt_min_interval_s`` and never within one camera command slot of a focus command (the link
is budgeted for focus first). The head model dead-reckons the commanded speeds from when the
camera takes them (bytes + half a field) and keeps within the quantisation of position replies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dffd.scheduler.actions import (
    Action,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
)
from dffd.scheduler.clock import TIME_EPS_S
from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.geometry import (
    nearest_speed_index,
    pixel_offset_to_deg,
    speed_of_index,
    step_index,
)
from dffd.scheduler.search import Search, SearchStatus
from dffd.scheduler.wire import PAN_TILT_POSITION_REPLY_BYTES, link_time_s

# Centroids further apart than this (s) do not make a velocity (the target was lost between).
MAX_VELOCITY_GAP_S = 0.5
# Pan/tilt controller. The quiet speed changes only when another code is nearer to ω̂ by this
# fraction of |ω̂| (at least of half the slowest speed): ω̂ is noisy, and every change of the
# speed run through measured frames changes their smear.
QUIET_CODE_HYSTERESIS = 0.15
# Hysteresis of a correction: it starts when the projected error exceeds the band and runs on
# while more than this fraction of the band is left.
CONTINUE_FRACTION = 0.25
# No position inquiry when a pan/tilt command is due within this time (s): the inquiry holds the
# pan/tilt socket for about a field plus its 11-byte reply (~28 ms at 9600 baud).
POLL_CLEARANCE_S = 0.04


class PanTiltHead:
    """Pan/tilt position model (dead reckoning between inquiries) and centring controller.

    Drive mode, per axis, with ω̂ the target's filtered angular velocity and e its angular error:

    * **Quiet code** q: the VISCA speed (0 included) nearest to ω̂, changed only when another code
      is clearly nearer (hysteresis). It runs through every exposure the core measures on, so the
      head adds only |speed(q) − ω| × exposure of smear there, the same on the frames of a burst.
    * **Corrections** run in the *free windows*: while the focus is in transit (those frames are
      centroid-only) or while no bursts run. The correction needed at the window's end is
      ``M = e + (ω̂ − q)(τ + lead)`` (τ: time left in the window); when ``|M|`` exceeds the band
      (hysteresis: once started, a correction runs until M is cancelled) another code c is run
      for ``T = M / (speed(c) − speed(q))``, then q again before the next measured exposure.
      ``|speed(c) − ω̂|`` is capped (the tracker predicts the image motion at constant velocity and
      searches ±12 px) unless the error itself is large (the old proportional gain applies then).
    * A target far off-centre (half-way to the frame edge) is corrected at once, quiet or not.

    A target slower than the slowest speed (2°/s) is thus followed by drive pulses in the focus
    transits (duty cycle between 0 and 2°/s), never by a speed held through the measured frames.

    With no target to follow, an armed :class:`~dffd.scheduler.search.Search` sweeps the range.
    """

    def __init__(self, config: SchedulerConfig) -> None:
        self.config = config
        self.busy = False  # one pan/tilt action outstanding at a time (its own VISCA socket)
        self.poll_due: float = 0.0
        self._seg = _Segment(0.0, 0.0, 0.0)
        self._prev_seg: _Segment | None = None  # in force until ``_seg.t0`` (command latency)
        self._last_cmd_t = -math.inf
        self._last_cmd: PanTiltDrive | PanTiltAbsolute | PanTiltStop | None = None
        self._target: tuple[float, float] | None = None  # target direction, pan/tilt frame, deg
        self._target_t = -math.inf  # exposure time of that direction
        # That direction was measured with the head at rest or driving, not mid-way through an
        # absolute move (see ``_mid_absolute_move``): only such directions make a velocity.
        self._target_steady = True
        self._velocity = (0.0, 0.0)  # filtered target angular velocity, deg/s
        self._stop_pending = False
        self._return_pending = False
        self._searching = False
        self._velocity_samples = 0
        self._track_rate: tuple[float, float] | None = None  # the 3D tracker's, deg/s
        self._track_rate_t = -math.inf
        self._eval_due = math.inf
        self._last_focus_cmd = -math.inf
        self._last_step = -math.inf
        self._quiet_code = [0, 0]  # per axis (pan, tilt): the speed run through measured frames
        self._correcting = [False, False]  # a correction is running on that axis
        self.search = Search(config)  # the sweep while automatic acquisition sees nothing

    # -- model ---------------------------------------------------------------------------------
    def _segment_at(self, t: float) -> _Segment:
        """The commanded motion in force at ``t`` (the last command's, once it reached the
        motors; the one before until then)."""
        seg = self._seg
        if t < seg.t0 and self._prev_seg is not None:
            return self._prev_seg
        return seg

    def at(self, t: float) -> tuple[float, float]:
        seg = self._segment_at(t)
        dt = max(0.0, t - seg.t0)
        if seg.goal is not None:
            cfg = self.config
            idx_p, idx_t = self._absolute_speeds()
            speed_p = speed_of_index(idx_p, cfg.pan_speeds_deg_s)
            speed_t = speed_of_index(idx_t, cfg.tilt_speeds_deg_s)
            return (
                _approach(seg.pan0, seg.goal[0], speed_p, dt),
                _approach(seg.tilt0, seg.goal[1], speed_t, dt),
            )
        return seg.pan0 + seg.rate[0] * dt, seg.tilt0 + seg.rate[1] * dt

    def anchor(self, t: float, pan: float, tilt: float) -> None:
        """Re-anchor the model on a position reply received at ``t``.

        The reply is quantised (``pan_tilt_resolution_deg``) and was sampled a reply's wire time
        before ``t``: the model is moved only as far as needed to agree with it (snapping to the
        reading would add ±½ count, 3.7 px at f = 31 mm, of noise to every tag and to ω̂).
        """
        cfg = self.config
        t_s = t - link_time_s(PAN_TILT_POSITION_REPLY_BYTES, cfg.baudrate)
        model = self.at(t_s)
        seg = self._segment_at(t_s)
        slack = [cfg.pan_tilt_resolution_deg / 2.0 + abs(r) * cfg.command_slot_s for r in seg.rate]
        pan0 = min(max(model[0], pan - slack[0]), pan + slack[0])
        tilt0 = min(max(model[1], tilt - slack[1]), tilt + slack[1])
        goal = seg.goal
        if goal is not None and (
            abs(pan - goal[0]) <= slack[0] and abs(tilt - goal[1]) <= slack[1]
        ):
            pan0, tilt0, goal = goal[0], goal[1], None
        self._seg = _Segment(t_s, pan0, tilt0, seg.rate, goal)
        self._prev_seg = None
        self.busy = False

    def focus_command_at(self, t: float) -> None:
        self._last_focus_cmd = t
        # A focus move opens a free window: look again as soon as the link slot allows.
        follow = self._target is not None and self.config.pan_tilt_mode == "drive"
        if follow:
            due = max(t + self.config.command_slot_s, self._last_cmd_t + self._min_interval())
            self._eval_due = min(self._eval_due, due)

    # -- target ----------------------------------------------------------------------------
    def on_centroid(
        self, t: float, centroid: tuple[float, float] | None, pan: float, tilt: float
    ) -> None:
        cfg = self.config
        if cfg.pan_tilt_mode == "off":
            return
        if centroid is None:
            self._on_no_centroid(t)
            return
        w, h = cfg.frame_size
        ex = cfg.pan_sign * pixel_offset_to_deg(
            centroid[0] - (w - 1) / 2.0, cfg.focal_length_mm, cfg.pixel_pitch_mm
        )
        ey = cfg.tilt_sign * pixel_offset_to_deg(
            (h - 1) / 2.0 - centroid[1], cfg.focal_length_mm, cfg.pixel_pitch_mm
        )
        # The target's direction in the pan/tilt frame at that exposure; the error *now* subtracts
        # the camera's own motion since then (the capture latency would otherwise overshoot).
        target = (pan + ex, tilt + ey)
        prev, prev_t = self._target, self._target_t
        steady = not self._mid_absolute_move(t)
        if (
            prev is not None
            and steady
            and self._target_steady
            and t > prev_t
            and t - prev_t <= MAX_VELOCITY_GAP_S
        ):
            # Target angular velocity (feed-forward): a first-order filter on the differences of
            # its direction; without it a P-controller trails a moving target by ω/K, which at
            # telephoto is more than the field of view. The first difference is taken as it is
            # (feed-forward from the first two centroids: a target crossing at 7°/s leaves a
            # ±3° field of view in under a second, no time to let a filter converge).
            dt = t - prev_t
            a = 1.0 if self._velocity_samples == 0 else min(1.0, dt / cfg.pan_tilt_velocity_tau_s)
            self._velocity_samples += 1
            vp = (target[0] - prev[0]) / dt
            vt = (target[1] - prev[1]) / dt
            self._velocity = (
                self._velocity[0] + a * (vp - self._velocity[0]),
                self._velocity[1] + a * (vt - self._velocity[1]),
            )
        elif prev is None:
            self._velocity = (0.0, 0.0)
            self._velocity_samples = 0
        self._target = target
        self._target_t = t
        self._target_steady = steady
        self.search.seen(t, self._velocity[0])
        self._stop_pending = False
        self._return_pending = False
        self._eval_due = min(self._eval_due, self._last_cmd_t + self._min_interval())

    def _mid_absolute_move(self, t: float) -> bool:
        """The model has the head mid-way through an absolute move at ``t``.

        The model runs an absolute move at its constant speed; the motors accelerate and brake,
        so mid-move the modelled direction is off by up to ~0.7° at the search's speed (a search
        view or the return to a lost target's direction: the simulated EVI-D100 measured 0.65°,
        48 px at f = 31 mm). A target first seen during such a slew keeps that direction, but
        its velocity waits for directions measured with the head at rest or driving: two
        slewing frames 1/30 s apart made −2.9°/s of a target crossing at +10°/s, the drive
        that followed ran the other way and lost it for 10 s.
        """
        goal = self._segment_at(t).goal
        return goal is not None and self.at(t) != goal

    def on_track_rate(self, t: float, rate_deg_s: tuple[float, float]) -> None:
        """The 3D tracker's pan/tilt rate of the target's direction at ``t`` (deg/s)."""
        self._track_rate = rate_deg_s
        self._track_rate_t = t

    def release(self) -> None:
        """Stop following: one stop, then nothing until a new centroid (no search, no sweep)."""
        seg = self._seg
        if self._target is not None or seg.rate != (0.0, 0.0) or seg.goal is not None:
            self._stop_pending = True
            self._eval_due = self._last_cmd_t + self._min_interval()
        self._return_pending = False
        self.search.disarm()
        self._forget_target()

    def arm_search(self, t: float) -> None:
        """Automatic acquisition from ``t``: sweep when nothing is seen for ``search_after_s``."""
        self.search.arm(t)
        self._eval_due = min(self._eval_due, t)

    def on_done(self, t: float) -> None:
        """The outstanding pan/tilt action ended at ``t`` (done, answered or failed)."""
        self.busy = False
        self.search.on_move_done(t)
        if self.search.sweeping:
            self._eval_due = min(self._eval_due, t)  # the dwell at the new view starts

    def search_status(self) -> SearchStatus | None:
        """The sweep's status while no target is followed (None: not armed, or following)."""
        return None if self._target is not None else self.search.status()

    @property
    def searching(self) -> bool:
        """The target is lost and the head is searching for it (coast or return)."""
        return self._searching

    def _on_no_centroid(self, t: float) -> None:
        """A frame without a contour: coast, then search, then return to the last direction.

        Up to ``pan_tilt_lost_s`` this is a transit blur or a brief occlusion: keep following the
        extrapolated direction. Up to ``pan_tilt_search_s`` more the target is lost: keep driving
        along its predicted path (it most likely left the field of view that way) while the core
        searches every frame. After that, one absolute move back to the last direction it was
        seen in, and hold there (the core keeps searching the whole frame).
        """
        cfg = self.config
        if self._target is None:
            return
        age = t - self._target_t
        if age <= cfg.pan_tilt_lost_s:
            return
        if age <= cfg.pan_tilt_lost_s + cfg.pan_tilt_search_s:
            self._searching = True
            return
        self._searching = False
        self._return_pending = True
        self._eval_due = self._last_cmd_t + self._min_interval()

    def _feedforward(self) -> tuple[float, float]:
        """The angular velocity fed forward: the tracker's when enabled and fresh (no older
        than the target's last centroid by more than ``MAX_VELOCITY_GAP_S``), else ω̂."""
        cfg = self.config
        if not cfg.pan_tilt_feedforward:
            return 0.0, 0.0
        rate = self._track_rate
        if (
            cfg.pan_tilt_track_feedforward
            and rate is not None
            and self._target_t - self._track_rate_t <= MAX_VELOCITY_GAP_S
        ):
            return rate
        return self._velocity

    def _forget_target(self) -> None:
        self._target = None
        self._track_rate = None
        self._velocity = (0.0, 0.0)
        self._velocity_samples = 0
        self._target_steady = True
        self._searching = False
        self._correcting = [False, False]

    # -- decisions -----------------------------------------------------------------------------
    def step(
        self, now: float, next_focus_cmd: float | None, quiet_at: float | None
    ) -> Action | None:
        cfg = self.config
        self._last_step = now
        if cfg.pan_tilt_mode == "off" or self.busy:
            return None
        # Budget the link: keep a camera command slot free around focus commands.
        slot = cfg.command_slot_s
        if now - self._last_focus_cmd < slot - TIME_EPS_S:
            return None
        if next_focus_cmd is not None and 0.0 <= next_focus_cmd - now < slot - TIME_EPS_S:
            return None
        if now >= self._eval_due - TIME_EPS_S:
            cmd, due = self._decide(now, quiet_at)
            if cmd is not None:
                self._apply(cmd, now)
                self.busy = True
                self._eval_due = max(due, now + self._min_interval())
                return cmd
            self._eval_due = due
        # An inquiry holds the socket for a field or two: not just before a planned command.
        if now >= self.poll_due and self._eval_due - now > POLL_CLEARANCE_S:
            self.poll_due = now + cfg.pan_tilt_poll_interval_s
            self.busy = True
            return PanTiltInquiry()
        return None

    def wakeup(self, next_focus_cmd: float | None) -> float | None:
        if self.config.pan_tilt_mode == "off" or self.busy:
            return None
        slot = self.config.command_slot_s
        poll = self.poll_due
        if self._eval_due - max(poll, self._last_step) <= POLL_CLEARANCE_S:
            poll = self._eval_due  # the inquiry waits behind that command (see ``step``)
        t = max(min(poll, self._eval_due), self._last_focus_cmd + slot, self._last_step)
        if next_focus_cmd is not None and 0.0 <= next_focus_cmd - t < slot - TIME_EPS_S:
            t = next_focus_cmd + slot  # deferred behind that focus command (see ``step``)
        return None if t == math.inf else t

    def _min_interval(self) -> float:
        return self.config.pan_tilt_min_interval_s

    def _decide(
        self, now: float, quiet_at: float | None
    ) -> tuple[PanTiltDrive | PanTiltAbsolute | PanTiltStop | None, float]:
        """The command due now (None: keep what runs) and when to look again."""
        cfg = self.config
        idle = math.inf
        if self._stop_pending:
            return PanTiltStop(), idle
        if self._return_pending and self._target is not None:
            # The bounded search found nothing: back to where the target was last seen.
            seen = self._target
            self._return_pending = False
            self._forget_target()
            self.search.restart_timer(now)  # hold there search_after_s before sweeping
            return PanTiltAbsolute(seen[0], seen[1], *self._absolute_speeds()), now
        if self._target is None:
            return self.search.decide(now, self.at(now), self._absolute_speeds())
        pan_now, tilt_now = self.at(now)
        ff = self._feedforward()
        # Extrapolate the target to now (bounded by the search horizon).
        ahead = min(max(0.0, now - self._target_t), cfg.pan_tilt_lost_s + cfg.pan_tilt_search_s)
        err_p = self._target[0] + ff[0] * ahead - pan_now
        err_t = self._target[1] + ff[1] * ahead - tilt_now
        dead = cfg.pan_tilt_deadband_deg
        if cfg.pan_tilt_mode == "absolute":
            return self._decide_absolute(err_p, err_t, ff, ahead), idle
        periodic = now + self._min_interval()
        ip, end_p = self._axis(0, err_p, ff[0], now, quiet_at, dead)
        it, end_t = self._axis(1, err_t, ff[1], now, quiet_at, dead)
        due = min(periodic, end_p, end_t)
        last = self._last_cmd
        rate = self._seg.rate if self._seg.goal is None else None
        if ip == 0 and it == 0:
            if rate == (0.0, 0.0) and not isinstance(last, PanTiltAbsolute):
                return None, due
            if isinstance(last, PanTiltStop):
                return None, due
            return PanTiltStop(), due
        if isinstance(last, PanTiltDrive) and (last.pan_speed, last.tilt_speed) == (ip, it):
            return None, due
        return PanTiltDrive(
            ip,
            it,
            speed_of_index(ip, cfg.pan_speeds_deg_s),
            speed_of_index(it, cfg.tilt_speeds_deg_s),
        ), due

    def _axis(  # noqa: PLR0917 - private, per-axis step of _decide
        self,
        axis: int,
        error: float,
        omega: float,
        now: float,
        quiet_at: float | None,
        band: float,
    ) -> tuple[int, float]:
        """Signed speed index for one axis and when its correction (if any) ends."""
        cfg = self.config
        table = cfg.pan_speeds_deg_s if axis == 0 else cfg.tilt_speeds_deg_s
        max_idx = len(table)
        q = self._quiet_code[axis]
        best = nearest_speed_index(omega, table)
        hysteresis = QUIET_CODE_HYSTERESIS * max(abs(omega), table[0] / 2.0)
        if (
            abs(speed_of_index(q, table) - omega)
            > abs(speed_of_index(best, table) - omega) + hysteresis
        ):
            q = best
        self._quiet_code[axis] = q
        sq = speed_of_index(q, table)
        emergency = abs(error) > cfg.pan_tilt_emergency_deg
        if quiet_at is None:
            tau = cfg.pan_tilt_horizon_s  # no measured exposures ahead: a rolling horizon
        else:
            tau = quiet_at - cfg.pan_tilt_latency_s - now
            if tau < self._min_interval():
                if not emergency:
                    self._correcting[axis] = False
                    return q, math.inf  # no time to correct and be back on q: keep q
                tau = cfg.pan_tilt_horizon_s
        # Error left at the window's end if q ran from now; aim at (q − ω̂)·lead there, so the
        # drift through the measured frames carries it across zero.
        m = error + (omega - sq) * (tau + cfg.pan_tilt_lead_s)
        threshold = band if not self._correcting[axis] else CONTINUE_FRACTION * band
        if abs(m) <= threshold:
            self._correcting[axis] = False
            return q, math.inf
        cap = max(cfg.pan_tilt_max_correction_deg_s, cfg.pan_tilt_gain_per_s * abs(error))
        u = min(max(m / tau, -cap), cap)
        c = nearest_speed_index(sq + u, table)
        direction = 1 if m > 0 else -1
        if (speed_of_index(c, table) - sq) * direction <= 0:
            c = step_index(q, direction, max_idx)  # at least one code towards the error
        relative = speed_of_index(c, table) - sq
        if relative == 0.0:
            self._correcting[axis] = False
            return q, math.inf  # at the end of the table: nothing faster to run
        duration = min(m / relative, tau)
        if duration < self._min_interval():
            if abs(m) < 0.5 * abs(relative) * self._min_interval():
                self._correcting[axis] = False
                return q, math.inf  # the shortest pulse would overshoot more than it corrects
            duration = self._min_interval()
        self._correcting[axis] = True
        return c, now + duration

    def _decide_absolute(
        self, err_p: float, err_t: float, ff: tuple[float, float], ahead: float
    ) -> PanTiltAbsolute | None:
        cfg = self.config
        assert self._target is not None
        dead = cfg.pan_tilt_deadband_deg
        if abs(err_p) <= dead and abs(err_t) <= dead:
            return None
        last = self._last_cmd
        if isinstance(last, PanTiltAbsolute) and (
            abs(last.pan_deg - self._target[0]) <= dead
            and abs(last.tilt_deg - self._target[1]) <= dead
        ):
            return None
        return PanTiltAbsolute(
            self._target[0] + ff[0] * ahead,
            self._target[1] + ff[1] * ahead,
            *self._absolute_speeds(),
        )

    def _absolute_speeds(self) -> tuple[int, int]:
        """Pan and tilt speed codes of absolute moves: the configured code, within each table."""
        cfg = self.config
        idx = cfg.absolute_speed_index
        return min(idx, len(cfg.pan_speeds_deg_s)), min(idx, len(cfg.tilt_speeds_deg_s))

    def _apply(self, cmd: PanTiltDrive | PanTiltAbsolute | PanTiltStop, now: float) -> None:
        # The motors change when the camera takes the command: after its bytes and, on average,
        # half a video field (the camera works on field boundaries).
        t_eff = now + self.config.pan_tilt_model_delay_s
        pan, tilt = self.at(t_eff)
        self._prev_seg = self._seg
        if isinstance(cmd, PanTiltDrive):
            self._seg = _Segment(t_eff, pan, tilt, rate=(cmd.pan_rate_deg_s, cmd.tilt_rate_deg_s))
        elif isinstance(cmd, PanTiltAbsolute):
            self._seg = _Segment(t_eff, pan, tilt, goal=(cmd.pan_deg, cmd.tilt_deg))
        else:
            self._seg = _Segment(t_eff, pan, tilt)
            self._stop_pending = False
        self._last_cmd = cmd
        self._last_cmd_t = now


@dataclass(frozen=True, slots=True)
class _Segment:
    """One commanded motion of the head model: from ``(pan0, tilt0)`` at ``t0`` either at
    ``rate`` (deg/s, drive) or towards ``goal`` at the absolute-move speed."""

    t0: float
    pan0: float
    tilt0: float
    rate: tuple[float, float] = (0.0, 0.0)
    goal: tuple[float, float] | None = None


def _approach(start: float, goal: float, speed: float, dt: float) -> float:
    step = speed * dt
    if abs(goal - start) <= step:
        return goal
    return start + math.copysign(step, goal - start)
