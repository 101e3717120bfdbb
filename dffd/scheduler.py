"""Frame scheduler: interleaves three-focus bursts with tracking frames and centres the target.

Pure and synchronous (DESIGN §1, §4): no I/O, no clock of its own, no asyncio. The daemon shell
feeds it events stamped with monotonic times and executes the actions it returns; the same
object runs live, in virtual time, and in the unit tests.

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

How a frame's focus is known. The focus is *stationary* from the moment a Completion is received
(the motor stopped before the camera said so) until the next move is issued (the lens cannot
move before its command is written). The scheduler keeps those stationary intervals; a frame is
``track``/``burst`` only if its whole exposure lies inside one of them with ``timing_margin_s``
to spare, otherwise ``transit``. Where that is not certain (a move timed out or failed, or the
start-up position is unknown) it issues :class:`FocusInquiry` until two readings agree (or one
equals the commanded target) and tags ``transit`` meanwhile.

How bursts are timed. Exposures are periodic; from the last delivered frame's timestamp and the
period the scheduler predicts the exposure windows of frames still in flight (capture latency)
and of future frames. For each burst slot it *claims* the first exposure that starts after the
focus settled, and issues the next move as soon as that exposure has *ended* — it does not wait
for the frame to be delivered, so the capture latency costs nothing in steady state. The claimed
frame is tagged ``burst`` with ``(burst id, slot)`` when it arrives; a claimed frame that never
arrives (dropped by the capture) leaves the burst incomplete (counted in :class:`SchedulerStats`).

Burst modes. ``rolling`` (the daemon's default): the focus runs a triangle lo, mid, hi, mid, lo, …
over the core's plan; ``max(1, burst_every_frames)`` tracking frames at the middle (the best focus,
so they are the tracking frames), then one exposure at the next end, alternating sides. Each end is
tagged ``burst`` with ``(id, 2)`` alone: it closes a burst with the previous end and the middle
frame between them (the core assembles it), so a depth comes every two half-bracket moves instead
of four plus the tracking frames. An end's counts are taken from the latest plan when its move is
issued (that plan carries the burst the core fitted at the frame before). On the reference
simulator this gives 2.2 Hz against 0.86 Hz for ``classic`` and 0.33 Hz for a full sweep
(docs/estimation.md §6). ``classic``: three settings per burst, mid → end → end → mid.

Burst policy: one burst after ``burst_every_frames`` tracking exposures at the tracking focus, or
earlier when the reported σ of ẑ exceeds ``sigma_trigger_m``. Slot order minimises motor travel
(including the return to the tracking focus); a planned setting within ``snap_fraction`` of the
plan's step (or ``snap_counts``) of the current focus is taken where the lens already is (the core
fits over the real counts in the tag). Between bursts the lens is re-focused only when the plan's
centre has moved by more than ``retarget_steps`` bracket steps: chasing estimate noise with focus
moves would cost transit frames and restart the tracking count.

Pan/tilt (drive mode; see :class:`_PanTilt`): the VISCA speed table is coarse (2.0°/s is the
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

Acquisition and loss. The core's burst plans are ignored until the contour has been seen on
``acquire_stable_frames`` consecutive frames (acquire first, then bursts). Frames without a
contour for up to ``pan_tilt_lost_s`` are coasted through (transit blur, brief occlusion); after
that the target is lost and the head *searches*: it keeps driving along the target's predicted
path for ``pan_tilt_search_s`` (a target that left the field of view most likely did so along
its motion), then returns to the direction where the target was last seen with one absolute move
and holds there. The core re-searches the frame throughout, so a target that comes back into
view is re-acquired and followed again.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Literal

from dffd.core.types import FrameTag

# -- VISCA link facts (DESIGN §5) -------------------------------------------------------------
BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
FOCUS_DIRECT_BYTES = 9  # 8x 01 04 48 0p 0q 0r 0s FF
ACK_BYTES = 3  # z0 4y FF
COMPLETION_BYTES = 3  # z0 5y FF
PAN_TILT_DRIVE_BYTES = 9  # 8x 01 06 01 VV WW XX YY FF
PAN_TILT_ABSOLUTE_BYTES = 15  # 8x 01 06 02 VV WW 0Y×4 0Z×4 FF
PAN_TILT_POSITION_REPLY_BYTES = 11  # z0 50 0w×4 0z×4 FF
# Pan/tilt speed table for VISCA speed indices 01…18 (deg/s), EVI-D100 reference model.
VISCA_SPEEDS_DEG_S: tuple[float, ...] = (
    2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0,
    27.0, 34.0, 42.0, 52.0, 65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0,
)  # fmt: skip
PAN_MAX_SPEED_INDEX = 0x18
TILT_MAX_SPEED_INDEX = 0x14

# Gains of the exposure-clock tracker (per delivered frame): the phase follows a timestamp
# step within ~5 frames, the period within ~100; jitter is averaged over as many frames.
PHASE_GAIN = 0.2
PERIOD_GAIN = 0.01
# Float rounding allowance when comparing times (s); far below any physical timing.
TIME_EPS_S = 1e-7
# Stationary-focus intervals kept for tagging late frames: at one move per frame this still covers
# several seconds, far more than any capture latency.
FOCUS_HISTORY = 64
# Centroids further apart than this (s) do not make a velocity (the target was lost between).
MAX_VELOCITY_GAP_S = 0.5
# Burst completion times kept for the achieved-rate estimate.
RATE_WINDOW = 64
# Exposure times of recent transit tags: the estimator's feedback arrives a few frames late at
# most (capture latency + estimator queue), far fewer than this.
TRANSIT_HISTORY = 32

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

PanTiltMode = Literal["drive", "absolute", "off"]
BurstMode = Literal["rolling", "classic"]
# Slot number in the tag of a rolling burst's end frame: it closes a burst whose slots 0 and 1 are
# the previous end (the other side of the bracket) and the tracking frame at the middle between.
ROLLING_SLOT = 2
# A rolling end closes a burst only if the previous end was this recent (s); an older one (a
# recovery, a loss, a policy pause in between) opens a new sequence instead.
ROLLING_MAX_SPAN_S = 2.0


@dataclass(frozen=True, slots=True, kw_only=True)
class SchedulerConfig:
    """Timing, policy and geometry the scheduler needs.

    Built from the service config by :func:`dffd.wiring.scheduler_config`: the fields it sets
    have no defaults here (the config's are the only ones); the rest are the scheduler's own.
    """

    fps: float
    # Exposure duration (s); None = the full frame period (the conservative assumption).
    exposure_s: float | None
    # Frames between exposure and delivery (measured by `dffd calibrate`); only the rate limit of
    # the non-predictive mode and the pan/tilt delay depend on it.
    capture_latency_frames: int
    # Bound on the error of frame timestamps (s): a frame counts as exposed off a focus move only
    # with this much to spare either side; covers capture timestamp jitter and reply transit.
    timing_margin_s: float
    # Burst policy. ``classic``: three settings mid → end → end → mid per burst, then
    # ``burst_every_frames`` tracking frames. ``rolling``: a triangle lo, mid, hi, mid, lo, … with
    # ``max(1, burst_every_frames)`` tracking frames at each pass through the middle; every
    # arrival at an end closes a burst with the previous end and the middle frame between.
    burst_mode: BurstMode
    burst_every_frames: int
    sigma_trigger_m: float | None
    snap_counts: int = 40
    snap_fraction: float = 0.25
    retarget_steps: float = 0.25
    # Focus motor and link timing.
    focus_speed_counts_per_s: float
    focus_tolerance_counts: int = 2
    baudrate: int
    # The camera accepts one command per video field (DESIGN §5: ~1V, 16.7 ms at 60 Hz).
    command_slot_s: float = 1.0 / 60.0
    initial_focus_counts: int | None = None
    focus_inquiry_interval_s: float = 0.05
    # Pan/tilt.
    pan_tilt_mode: PanTiltMode
    focal_length_mm: float
    pixel_pitch_mm: float
    frame_size: tuple[int, int]
    pan_tilt_gain_per_s: float  # commanded deg/s per degree of error
    pan_tilt_feedforward: bool  # add the target's filtered angular velocity
    pan_tilt_velocity_tau_s: float = 0.3  # time constant of that velocity filter
    pan_tilt_lost_s: float  # no centroid for this long: the target is lost → search
    # Search after a loss: keep driving towards the target's extrapolated direction (its last
    # direction plus its filtered angular velocity times the time since) for this long, then
    # return to the last direction it was seen in and hold there (0: hold at once).
    pan_tilt_search_s: float
    # Consecutive frames with a contour before the core's burst plans are followed: bursts (long
    # focus travel, transit frames) start only once the contour is stable (0: no such gate).
    acquire_stable_frames: int
    # Hysteresis band (deg): a correction starts when the error projected to the end of the free
    # window exceeds it, and runs until that error is cancelled.
    pan_tilt_deadband_deg: float
    # Cap on |correction speed − ω̂| (deg/s) unless the proportional gain asks for more: the core's
    # tracker predicts image motion at constant velocity and searches ±12 px along its normals
    # (12 px × 30 fps ≈ 3.3°/s at f = 31 mm, 5 µm pixels).
    pan_tilt_max_correction_deg_s: float
    # Aim of a correction: the error left when the quiet speed resumes is (q − ω̂)·lead, so the
    # drift through the measured frames carries it across zero (~half a rolling-bracket cycle).
    pan_tilt_lead_s: float = 0.2
    # Correction horizon while no bursts run (acquisition): no measured exposures to keep clear.
    pan_tilt_horizon_s: float = 0.3
    # Position resolution of the head (deg): EVI-D100 14.4 counts/°. Inquiry replies are
    # quantised to it; the model is kept within it rather than snapped.
    pan_tilt_resolution_deg: float = 1.0 / 14.4
    pan_tilt_min_interval_s: float
    pan_tilt_poll_interval_s: float = 0.25
    absolute_speed_index: int = 0x10
    pan_sign: int = 1  # +1: image x to the right is positive pan
    tilt_sign: int = 1  # +1: image y upwards is positive tilt

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"fps must be > 0 (got {self.fps})")
        if self.exposure_s is not None and not 0 < self.exposure_s <= 1.0 / self.fps:
            raise ValueError(f"exposure_s must be in (0, 1/fps] (got {self.exposure_s})")
        if self.burst_every_frames < 0:
            raise ValueError(f"burst_every_frames must be >= 0 (got {self.burst_every_frames})")
        if self.burst_mode not in ("rolling", "classic"):
            raise ValueError(f"burst_mode must be 'rolling' or 'classic' (got {self.burst_mode!r})")
        if self.focus_speed_counts_per_s <= 0:
            raise ValueError("focus_speed_counts_per_s must be > 0")
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be > 0 (got {self.baudrate})")
        if self.pan_sign not in (1, -1) or self.tilt_sign not in (1, -1):
            raise ValueError("pan_sign and tilt_sign must be +1 or -1")
        if self.pan_tilt_search_s < 0 or self.pan_tilt_lost_s < 0:
            raise ValueError("pan_tilt_lost_s and pan_tilt_search_s must be >= 0")
        if self.acquire_stable_frames < 0:
            raise ValueError("acquire_stable_frames must be >= 0")

    @property
    def period_s(self) -> float:
        """Nominal frame period."""
        return 1.0 / self.fps

    @property
    def guard_s(self) -> float:
        """Scheduling guard around a claimed exposure: the tag check's margin plus the
        prediction's own error bound (both ``timing_margin_s``), so a claimed frame passes the
        check even when its timestamp arrives off by the margin."""
        return 2.0 * self.timing_margin_s

    @property
    def exposure(self) -> float:
        """Exposure duration used for tagging (s)."""
        return self.exposure_s if self.exposure_s is not None else self.period_s

    @property
    def pan_tilt_latency_s(self) -> float:
        """Longest time from writing a Pan-tiltDrive to the motors changing: its bytes, then up
        to one camera command slot (the camera takes commands at field boundaries), plus the
        timing margin."""
        return (
            link_time_s(PAN_TILT_DRIVE_BYTES, self.baudrate)
            + self.command_slot_s
            + self.timing_margin_s
        )

    @property
    def pan_tilt_model_delay_s(self) -> float:
        """Mean time from writing a pan/tilt command to the motors changing (the model's)."""
        return link_time_s(PAN_TILT_DRIVE_BYTES, self.baudrate) + self.command_slot_s / 2.0

    @property
    def pan_tilt_emergency_deg(self) -> float:
        """Error (deg) corrected at once, measured frames or not: half-way to the nearer frame
        edge."""
        half = min(self.frame_size) / 4.0
        return pixel_offset_to_deg(half, self.focal_length_mm, self.pixel_pitch_mm)


# -- actions ----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class FocusMove:
    """Focus Direct to ``counts``; report Completion with ``on_focus_completed(move_id, t)``."""

    move_id: int
    counts: int


@dataclass(frozen=True, slots=True)
class FocusInquiry:
    """FocusPosInq; report the reply with ``on_focus_position(t, counts)``."""


@dataclass(frozen=True, slots=True)
class PanTiltDrive:
    """Pan-tiltDrive: signed VISCA speed indices (0 = stop that axis) and their rates in deg/s."""

    pan_speed: int
    tilt_speed: int
    pan_rate_deg_s: float
    tilt_rate_deg_s: float


@dataclass(frozen=True, slots=True)
class PanTiltAbsolute:
    """Absolute pan/tilt move (degrees) at VISCA speed indices."""

    pan_deg: float
    tilt_deg: float
    pan_speed: int
    tilt_speed: int


@dataclass(frozen=True, slots=True)
class PanTiltStop:
    """Stop both pan/tilt axes."""


@dataclass(frozen=True, slots=True)
class PanTiltInquiry:
    """Pan-tiltPosInq; report with ``on_pan_tilt_position(t, pan_deg, tilt_deg)``."""


Action = FocusMove | FocusInquiry | PanTiltDrive | PanTiltAbsolute | PanTiltStop | PanTiltInquiry
PAN_TILT_ACTIONS = (PanTiltDrive, PanTiltAbsolute, PanTiltStop, PanTiltInquiry)


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


# -- theoretical rate -------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class RateLimit:
    """The depth-measurement rate an ideal scheduler reaches with this configuration."""

    depth_hz: float
    cycle_frames: int  # frame periods per measurement cycle (bursts + tracking)
    move_frames: tuple[int, ...]  # frame periods each focus move of a burst costs
    move_s: tuple[float, ...]  # command → Completion time of each move
    predictive: bool


def link_time_s(n_bytes: int, baudrate: int) -> float:
    """Time to clock ``n_bytes`` through an 8N1 serial line."""
    return n_bytes * BITS_PER_BYTE / baudrate


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
    config: SchedulerConfig, spacing_counts: int, *, predictive: bool = True
) -> RateLimit:
    """Theoretical depth measurements per second for brackets ``c−s, c, c+s`` (DESIGN §8).

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
    spacing = abs(int(spacing_counts))
    period = config.period_s
    wait = config.exposure + 2.0 * config.guard_s
    if not predictive:
        wait += config.capture_latency_frames * period
    rolling = config.burst_mode == "rolling"
    if rolling:
        moves: tuple[int, ...] = (spacing, spacing) if spacing else ()
    else:
        moves = (spacing, 2 * spacing, spacing) if spacing else ()
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


# -- geometry and speed helpers ---------------------------------------------------------------
def pixel_offset_to_deg(offset_px: float, focal_length_mm: float, pixel_pitch_mm: float) -> float:
    """Angle (deg) off the optical axis of an image point ``offset_px`` from the centre."""
    return math.degrees(math.atan2(offset_px * pixel_pitch_mm, focal_length_mm))


def visca_speed_index(rate_deg_s: float, max_index: int) -> int:
    """Signed VISCA speed index whose table speed is nearest (log scale) to ``rate_deg_s``.

    Returns 0 only for a zero rate: any non-zero rate maps to at least index 1 (speed 00 is a
    syntax error on some models, DESIGN §5).
    """
    if rate_deg_s == 0.0 or not math.isfinite(rate_deg_s):
        return 0
    magnitude = abs(rate_deg_s)
    table = VISCA_SPEEDS_DEG_S[:max_index]
    best = min(range(len(table)), key=lambda i: abs(math.log(table[i] / magnitude)))
    return int(math.copysign(best + 1, rate_deg_s))


def speed_of_index(index: int) -> float:
    """Signed deg/s of a signed VISCA speed index (0 → 0)."""
    if index == 0:
        return 0.0
    return math.copysign(VISCA_SPEEDS_DEG_S[abs(index) - 1], index)


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


# -- the scheduler ----------------------------------------------------------------------------
@dataclass(slots=True)
class _Dwell:
    """The focus was stationary at ``counts`` over ``[t0, t1)``."""

    t0: float
    t1: float
    counts: int


@dataclass(slots=True)
class _Move:
    move_id: int
    target: int
    t_issued: float
    t_done: float = math.inf  # predicted Completion (``focus_move_time_s``); inf: unknown


@dataclass(slots=True)
class _Burst:
    burst_id: int
    order: tuple[int, ...]
    slot: int = 0  # the slot being acquired
    claims: list[float] = field(default_factory=list)  # predicted exposure mid-time per slot
    tagged: list[bool] = field(default_factory=list)
    start_at: float = -math.inf  # first move not before (the last tracking exposure's end)
    tag_slots: tuple[int, ...] = ()  # slot numbers in the tags (default: 0, 1, 2, …)
    rolling: bool = False
    side: int = 0  # rolling: +1 the plan's high end, −1 its low end


Phase = Literal[
    "init", "track", "burst_wait", "burst_move", "burst_dwell", "return_move", "recover"
]

# Frames beyond the capture latency without a delivery before the capture counts as stalled.
STALL_FRAMES = 3
# Bursts whose claimed frames are still in flight (capture latency): a few at most.
PENDING_BURSTS = 8


class Scheduler:
    """Decides focus and pan/tilt commands and tags frames; see the module docstring."""

    def __init__(self, config: SchedulerConfig) -> None:
        self.config = config
        self.stats = SchedulerStats()
        self._phase: Phase = "init"
        self._dwells: deque[_Dwell] = deque(maxlen=FOCUS_HISTORY)
        self._move: _Move | None = None
        self._next_move_id = 1
        self._burst: _Burst | None = None  # the burst whose moves are being executed
        self._pending: deque[_Burst] = deque(maxlen=PENDING_BURSTS)  # claims awaiting frames
        self._next_burst_id = 1
        self._burst_times: deque[float] = deque(maxlen=RATE_WINDOW)
        # Focus knowledge.
        self._counts: int | None = None  # stationary counts, if known
        self._track_counts: int | None = config.initial_focus_counts
        self._track_from = -math.inf  # tracking exposures count from this time
        self._inquiry_due = 0.0
        self._inquiry_pending = False
        self._last_reading: int | None = None
        # Frame timing.
        self._t_ref: float | None = None  # the last delivered exposure mid-time
        self._period = config.period_s
        self._last_index: int | None = None
        self._last_tagged_mid = -math.inf
        # Estimator feedback.
        self._plan: tuple[int, ...] | None = None
        self._sigma: float | None = None
        self._burst_now = False
        self._stable = 0  # consecutive frames with a centroid (acquisition)
        self._centroid_t = -math.inf
        # Rolling bracket: the side of the next end (+1 high counts, −1 low), when the last end
        # was tagged, and whether a tracking frame (the middle) was tagged since.
        self._rolling_side = -1
        self._rolling_end_t: float | None = None
        self._track_since_end = False
        self._transit_ts: deque[float] = deque(maxlen=TRANSIT_HISTORY)
        # Pan/tilt.
        self._pt = _PanTilt(config)

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
        return self._period

    @property
    def searching(self) -> bool:
        """The target is lost and pan/tilt is searching along its predicted path."""
        return self._pt.searching

    def pan_tilt_at(self, t: float) -> tuple[float, float]:
        """Model pan/tilt (deg) at time ``t``."""
        return self._pt.at(t)

    def achieved_rate_hz(self, now: float, window_s: float = 10.0) -> float:
        """Completed bursts per second over the last ``window_s`` seconds."""
        recent = [t for t in self._burst_times if now - t <= window_s]
        if len(recent) < 2:
            return 0.0
        span = recent[-1] - recent[0]
        return (len(recent) - 1) / span if span > 0 else 0.0

    # -- frame events -----------------------------------------------------------------------
    def on_frame(self, index: int, t: float) -> FrameTag:
        """Tag the frame exposed around mid-time ``t`` (delivered now).

        ``track``: whole exposure at a known, stationary focus that is not a claimed burst slot
        (normally the tracking focus); ``burst``: a claimed slot; ``transit``: the focus moved (or
        may have moved, or was unknown) during the exposure.
        """
        self._update_timing(index, t)
        pan, tilt = self._pt.at(t)
        half = self.config.exposure / 2.0
        counts = self._counts_during(t - half, t + half)
        tag: FrameTag
        if counts is None:
            tag = FrameTag("transit", None, pan, tilt)
        else:
            slot = self._claim_for(t, counts)
            if slot is not None:
                tag = FrameTag("burst", counts, pan, tilt, slot)
            elif self._inside_burst(t):
                # An unclaimed frame between a burst's slots (exposed whole at a burst setting):
                # a ``track`` tag would end the burst early in the core, so centroid only.
                tag = FrameTag("transit", None, pan, tilt)
            else:
                tag = FrameTag("track", counts, pan, tilt)
        if tag.role == "track":
            self._track_since_end = True
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
        self._pt.busy = False

    def on_pan_tilt_failed(self, t: float) -> None:
        """The last pan/tilt action failed; the model is re-anchored by the next inquiry."""
        self._pt.busy = False
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
    ) -> None:
        """Feedback from the core for the frame exposed at ``t``.

        ``plan``: the next burst's settings (``Pipeline.plan_burst``), None while the core has no
        depth to bracket (no bursts then). ``centroid_px``: the target's image centroid, None when
        lost (pan/tilt stops). ``pan_deg``/``tilt_deg``: the tag's pan/tilt for that exposure.
        """
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
            # of its own, which must not cancel the last one (measured: the rolling bracket lost
            # one frame per pass waiting for the next tracking frame's plan).
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
        """Tracking focus to use until the core plans bursts (e.g. from an initial depth)."""
        self._track_counts = int(counts)

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
        """Stop following the target: one stop is issued, then nothing until a new centroid."""
        self._pt.release()

    # -- decisions --------------------------------------------------------------------------
    def next_actions(self, now: float) -> list[Action]:
        """Actions due at ``now``; the shell executes them in order (focus first)."""
        actions: list[Action] = []
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
        if self._plan is None or self._t_ref is None or self._phase in ("init", "recover"):
            return None
        move = self._move
        if move is None:
            return now
        if move.t_done == math.inf:
            return now  # unknown travel: assume it ends at once (no correction in its shadow)
        mid = self._first_mid_starting_after(move.t_done + self.config.guard_s)
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
            home = self._track_counts
            if home is not None and abs(home - self._counts) > self._retarget_threshold():
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
                # the burst the core fitted there (committing at the claim used a plan one burst
                # older: measured raw z_m std 30 → 45 mm on paper-circle).
                burst.order = (self._plan[-1] if burst.side > 0 else self._plan[0],)
            return self._issue_move(burst.order[0], now, "burst_move")
        if self._phase == "burst_dwell":
            burst = self._burst
            assert burst is not None
            if now < self._claim_end(burst.claims[burst.slot]) + self.config.guard_s:
                return None
            return self._advance_burst(now)
        return None

    def _focus_wakeup(self) -> float | None:
        """When the focus machine must be looked at again (None: on the next event)."""
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
            return self._claim_end(self._burst.claims[self._burst.slot]) + margin
        if self._phase == "burst_wait" and self._burst is not None:
            return self._burst.start_at
        if self._phase == "track" and self._plan is not None and self._t_ref is not None:
            claim = self._track_claim_mid(now)
            if claim is not None:
                due = self._claim_end(claim) + margin
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
        if self._t_ref is None or not self._frames_flowing(now):
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
        assert self._t_ref is not None
        cfg = self.config
        expected_age = (cfg.capture_latency_frames + STALL_FRAMES) * self._period + cfg.exposure
        return now - self._t_ref <= expected_age

    def _track_claim_mid(self, now: float | None) -> float | None:
        """Mid-time of the tracking exposure that becomes the next burst's first slot."""
        if self._counts is None or self._t_ref is None:
            return None
        first = self._first_mid_starting_after(self._track_from)
        eligible = max(first, self._next_mid_after(self._last_tagged_mid))
        if self._burst_now:
            if now is None:
                return eligible
            latest = self._last_mid_ending_before(now - self.config.guard_s)
            return max(eligible, latest)
        every = self.config.burst_every_frames
        if self.config.burst_mode == "rolling":
            # The claimed exposure is the last of the tracking frames at the middle.
            every = max(1, every) - 1
        return max(eligible, first + every * self._period)

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
            burst = _Burst(
                self._next_burst_id, order, tag_slots=(ROLLING_SLOT,), rolling=True,
                side=-self._rolling_side,
            )  # fmt: skip
        else:
            settings = list(self._plan)
            # Take a planned setting where the lens already is (the tag carries the real counts).
            nearest = min(range(len(settings)), key=lambda i: abs(settings[i] - current))
            if abs(settings[nearest] - current) <= self._snap_threshold():
                settings[nearest] = current
            home = self._track_counts if self._track_counts is not None else current
            order = order_settings(current, tuple(settings), home, self.config)
            burst = _Burst(self._next_burst_id, order)
        self._next_burst_id += 1
        self._burst = burst
        self._pending.append(burst)
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
            burst.start_at = self._claim_end(claim_mid) + self.config.guard_s
            self._phase = "burst_wait"
        return self._focus_step(now)

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
        home = self._track_counts if self._track_counts is not None else burst.order[-1]
        assert self._counts is not None
        if abs(home - self._counts) <= self.config.focus_tolerance_counts:
            self._phase = "track"
            self._track_from = self._claim_end(burst.claims[-1])
            return None
        return self._issue_move(home, now, "return_move")

    def _claim_after(self, t: float) -> None:
        """Claim the first exposure starting after ``t`` (+margin) for the current slot."""
        burst = self._burst
        assert burst is not None
        start = t + self.config.guard_s
        mid = self._first_mid_starting_after(start) if self._t_ref is not None else start
        mid = max(mid, self._next_mid_after(self._last_tagged_mid))
        burst.claims.append(mid)
        burst.tagged.append(False)
        self._phase = "burst_dwell"

    def _issue_move(self, target: int, now: float, phase: Phase) -> FocusMove:
        move = _Move(self._next_move_id, int(target), now)
        if self._counts is not None:
            move.t_done = now + focus_move_time_s(self.config, int(target) - self._counts)
        self._next_move_id += 1
        self._move = move
        self._phase = phase
        if self._dwells and self._dwells[-1].t1 == math.inf:
            self._dwells[-1].t1 = now  # the lens may move from the moment it is commanded
        self._counts = None
        self.stats.focus_moves += 1
        return FocusMove(move.move_id, move.target)

    def _settle(self, counts: int, t: float) -> None:
        phase = self._phase
        self._move = None
        self._counts = int(counts)
        self._last_reading = None
        self._inquiry_pending = False
        self._dwells.append(_Dwell(t, math.inf, int(counts)))
        if phase == "burst_move" and self._burst is not None:
            self._claim_after(t)
        else:
            self._phase = "track"
            self._track_from = t + self.config.guard_s

    def _enter_recover(self, t: float) -> None:
        if self._dwells and self._dwells[-1].t1 == math.inf:
            self._dwells[-1].t1 = t
        self._move = None
        self._counts = None
        self._phase = "recover"
        self._last_reading = None
        self._inquiry_pending = False
        self._inquiry_due = t
        if self._burst is not None:
            self._fail(self._burst)

    def _fail(self, burst: _Burst) -> None:
        """A burst cannot complete: forget its claims (its frames are tagged ``track``)."""
        if burst in self._pending:
            self._pending.remove(burst)
            self.stats.bursts_incomplete += 1
        if burst.rolling:
            self._rolling_end_t = None  # the core lacks that end: the next one opens anew
        if burst is self._burst:
            self._burst = None
            if self._phase in ("burst_dwell", "burst_wait"):
                self._phase = "track"
                self._track_from = -math.inf if self._counts is None else self._dwells[-1].t0
            elif self._phase == "burst_move":
                self._phase = "return_move"

    # -- internals: frame timing and tags ---------------------------------------------------
    def _update_timing(self, index: int, t: float) -> None:
        """Phase-locked estimate of the exposure clock: smooths timestamp jitter out of the
        predictions (a single late timestamp must not shift every future claim)."""
        if self._t_ref is None or self._last_index is None or index <= self._last_index:
            self._t_ref, self._last_index = t, index
            return
        steps = index - self._last_index
        predicted = self._t_ref + steps * self._period
        innovation = t - predicted
        if abs(innovation) < self._period / 2.0:
            self._t_ref = predicted + PHASE_GAIN * innovation
            period = self._period + PERIOD_GAIN * innovation / steps
            nominal = self.config.period_s
            self._period = min(max(period, 0.8 * nominal), 1.25 * nominal)
        else:
            self._t_ref = t  # a stall or a clock step: re-lock on this frame
        self._last_index = index

    def _first_mid_starting_after(self, t: float) -> float:
        """Mid-time of the first predicted exposure that starts at or after ``t``."""
        assert self._t_ref is not None
        half = self.config.exposure / 2.0
        k = math.ceil((t + half - self._t_ref) / self._period - 1e-9)
        return self._t_ref + k * self._period

    def _last_mid_ending_before(self, t: float) -> float:
        """Mid-time of the last predicted exposure that ends at or before ``t``."""
        assert self._t_ref is not None
        half = self.config.exposure / 2.0
        k = math.floor((t - half - self._t_ref) / self._period + 1e-9)
        return self._t_ref + k * self._period

    def _next_mid_after(self, mid: float) -> float:
        """Mid-time of the predicted exposure after the one at ``mid`` (−inf: none tagged yet)."""
        if mid == -math.inf or self._t_ref is None:
            return -math.inf
        k = math.floor((mid - self._t_ref) / self._period + 0.5) + 1
        return self._t_ref + k * self._period

    def _claim_end(self, mid: float) -> float:
        return mid + self.config.exposure / 2.0

    def _counts_during(self, a: float, b: float) -> int | None:
        # The next move is issued exactly ``margin`` after a claimed exposure ends: compare with
        # a tolerance far below any timing that matters so rounding cannot lose that frame.
        margin = self.config.timing_margin_s - TIME_EPS_S
        for dwell in reversed(self._dwells):
            if dwell.t0 + margin <= a and b <= dwell.t1 - margin:
                return dwell.counts
            if dwell.t1 <= a:
                break
        return None

    def _claim_for(self, t: float, counts: int) -> tuple[int, int] | None:
        tol = self._period / 2.0
        for burst in self._pending:
            for slot, mid in enumerate(burst.claims):
                if burst.tagged[slot] or abs(t - mid) >= tol or counts != burst.order[slot]:
                    continue
                burst.tagged[slot] = True
                if len(burst.claims) == len(burst.order) and all(burst.tagged):
                    self._pending.remove(burst)
                    if not burst.rolling or self._closes_rolling(t):
                        self.stats.bursts_completed += 1
                        self._burst_times.append(t)
                    else:
                        self.stats.rolling_openings += 1
                tag_slot = burst.tag_slots[slot] if burst.tag_slots else slot
                return (burst.burst_id, tag_slot)
        return None

    def _closes_rolling(self, t: float) -> bool:
        """A rolling end tagged at ``t`` closes a burst (a recent previous end, a middle frame
        between); either way it becomes the previous end of the next one."""
        prev = self._rolling_end_t
        closes = prev is not None and t - prev <= ROLLING_MAX_SPAN_S and self._track_since_end
        self._rolling_end_t = t
        self._track_since_end = False
        return closes

    def _inside_burst(self, t: float) -> bool:
        """``t`` lies after a burst's first claimed exposure and before its last one."""
        tol = self._period / 2.0
        for burst in self._pending:
            if not burst.claims or t <= burst.claims[0] + tol:
                continue
            complete = len(burst.claims) == len(burst.order)
            if not complete or t < burst.claims[-1] - tol:
                return True
        return False

    def _drop_missed_claims(self, t: float) -> None:
        tol = self._period / 2.0
        for burst in list(self._pending):
            if any(
                not done and t >= mid + tol
                for mid, done in zip(burst.claims, burst.tagged, strict=True)
            ):
                self._fail(burst)


@dataclass(frozen=True, slots=True)
class _Segment:
    """One commanded motion of the head model: from ``(pan0, tilt0)`` at ``t0`` either at
    ``rate`` (deg/s, drive) or towards ``goal`` at the absolute-move speed."""

    t0: float
    pan0: float
    tilt0: float
    rate: tuple[float, float] = (0.0, 0.0)
    goal: tuple[float, float] | None = None


class _PanTilt:
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
        self._velocity = (0.0, 0.0)  # filtered target angular velocity, deg/s
        self._stop_pending = False
        self._return_pending = False
        self._searching = False
        self._velocity_samples = 0
        self._eval_due = math.inf
        self._last_focus_cmd = -math.inf
        self._last_step = -math.inf
        self._quiet_code = [0, 0]  # per axis (pan, tilt): the speed run through measured frames
        self._correcting = [False, False]  # a correction is running on that axis

    # -- model ---------------------------------------------------------------------------------
    def at(self, t: float) -> tuple[float, float]:
        seg = self._seg
        if t < seg.t0 and self._prev_seg is not None:
            seg = self._prev_seg  # the last command has not reached the motors yet
        dt = max(0.0, t - seg.t0)
        if seg.goal is not None:
            idx = self.config.absolute_speed_index
            speed_p = speed_of_index(idx)
            speed_t = speed_of_index(min(idx, TILT_MAX_SPEED_INDEX))
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
        seg = self._seg if t_s >= self._seg.t0 or self._prev_seg is None else self._prev_seg
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
        if prev is not None and t > prev_t and t - prev_t <= MAX_VELOCITY_GAP_S:
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
        self._stop_pending = False
        self._return_pending = False
        self._eval_due = min(self._eval_due, self._last_cmd_t + self._min_interval())

    def release(self) -> None:
        """Stop following: one stop, then nothing until a new centroid (no search)."""
        seg = self._seg
        if self._target is not None or seg.rate != (0.0, 0.0) or seg.goal is not None:
            self._stop_pending = True
            self._eval_due = self._last_cmd_t + self._min_interval()
        self._return_pending = False
        self._forget_target()

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

    def _forget_target(self) -> None:
        self._target = None
        self._velocity = (0.0, 0.0)
        self._velocity_samples = 0
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
            idx = cfg.absolute_speed_index
            return PanTiltAbsolute(seen[0], seen[1], idx, min(idx, TILT_MAX_SPEED_INDEX)), idle
        if self._target is None:
            return None, idle
        pan_now, tilt_now = self.at(now)
        ff = self._velocity if cfg.pan_tilt_feedforward else (0.0, 0.0)
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
        return PanTiltDrive(ip, it, speed_of_index(ip), speed_of_index(it)), due

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
        max_idx = PAN_MAX_SPEED_INDEX if axis == 0 else TILT_MAX_SPEED_INDEX
        q = self._quiet_code[axis]
        best = nearest_speed_index(omega, max_idx)
        hysteresis = QUIET_CODE_HYSTERESIS * max(abs(omega), VISCA_SPEEDS_DEG_S[0] / 2.0)
        if abs(speed_of_index(q) - omega) > abs(speed_of_index(best) - omega) + hysteresis:
            q = best
        self._quiet_code[axis] = q
        sq = speed_of_index(q)
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
        c = nearest_speed_index(sq + u, max_idx)
        direction = 1 if m > 0 else -1
        if (speed_of_index(c) - sq) * direction <= 0:
            c = _step_index(q, direction, max_idx)  # at least one code towards the error
        relative = speed_of_index(c) - sq
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
        idx = cfg.absolute_speed_index
        return PanTiltAbsolute(
            self._target[0] + ff[0] * ahead,
            self._target[1] + ff[1] * ahead,
            idx,
            min(idx, TILT_MAX_SPEED_INDEX),
        )

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


def nearest_speed_index(rate_deg_s: float, max_index: int) -> int:
    """Signed VISCA speed index nearest to ``rate_deg_s``, 0 (stopped) included: rates below half
    the slowest speed map to 0, others as :func:`visca_speed_index`."""
    if abs(rate_deg_s) < VISCA_SPEEDS_DEG_S[0] / 2.0:
        return 0
    return visca_speed_index(rate_deg_s, max_index)


def _step_index(index: int, direction: int, max_index: int) -> int:
    """The signed speed index one code from ``index`` in ``direction`` (through 0)."""
    stepped = index + direction
    return max(-max_index, min(max_index, stepped))


def _approach(start: float, goal: float, speed: float, dt: float) -> float:
    step = speed * dt
    if abs(goal - start) <= step:
        return goal
    return start + math.copysign(step, goal - start)
