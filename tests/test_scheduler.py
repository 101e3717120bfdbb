"""Scheduler: frame tags, burst timing, rate limit, link budget and pan/tilt control.

Most tests drive the pure scheduler with a small discrete-event model of the camera written here
independently (motor as a function of time, link delays, periodic exposures delivered after a
capture latency, seeded jitter and drops) and check every tag against that model's truth.
"""

from __future__ import annotations

import heapq
import itertools
import math
import random
from dataclasses import dataclass, field, replace

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dffd.core.types import FrameTag
from dffd.scheduler import (
    FocusInquiry,
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
    Scheduler,
    SchedulerConfig,
    depth_rate_limit,
    focus_move_time_s,
    link_time_s,
    nearest_speed_index,
    order_settings,
    pixel_offset_to_deg,
    speed_of_index,
    visca_speed_index,
)
from drivers.visca.camera import EVI_D100

# Every field the service config sets is given (SchedulerConfig has no defaults for them):
# classic bursts, no pan/tilt, a 4 mm lens, 9600 baud.
BASE = SchedulerConfig(
    fps=30.0,
    exposure_s=None,
    capture_latency_frames=2,
    timing_margin_s=0.003,
    burst_mode="classic",
    burst_every_frames=6,
    sigma_trigger_m=None,
    focus_speed_counts_per_s=20000.0,
    baudrate=9600,
    focal_length_mm=4.0,
    pixel_pitch_mm=0.006,
    frame_size=(640, 480),
    pan_tilt_mode="off",
    pan_speeds_deg_s=EVI_D100.pan_speeds_deg_s,
    tilt_speeds_deg_s=EVI_D100.tilt_speeds_deg_s,
    pan_tilt_gain_per_s=1.5,
    pan_tilt_feedforward=True,
    pan_tilt_lost_s=0.5,
    pan_tilt_search_s=2.0,
    acquire_stable_frames=0,
    pan_tilt_deadband_deg=0.15,
    pan_tilt_max_correction_deg_s=3.0,
    pan_tilt_min_interval_s=0.1,
    initial_focus_counts=5000,
)
PLAN = (4700, 5000, 5300)
# The reference camera's pan and tilt speed tables (codes 01…18 and 01…14).
PAN = EVI_D100.pan_speeds_deg_s
TILT = EVI_D100.tilt_speeds_deg_s


# -- a model camera, independent of the scheduler ----------------------------------------------
@dataclass
class Motor:
    """Focus position as piecewise-linear segments (t0, c0, t1, c1)."""

    segments: list[tuple[float, float, float, float]] = field(default_factory=list)

    def position(self, t: float) -> float:
        for t0, c0, t1, c1 in reversed(self.segments):
            if t >= t0:
                if t >= t1:
                    return c1
                return c0 + (c1 - c0) * (t - t0) / (t1 - t0)
        return self.segments[0][1]

    def moved_during(self, a: float, b: float) -> bool:
        return any(t0 < b and t1 > a and c0 != c1 for t0, c0, t1, c1 in self.segments)


@dataclass
class Harness:
    config: SchedulerConfig
    seed: int = 1
    jitter_s: float = 0.0  # timestamp noise of delivered frames
    drop: set[int] = field(default_factory=set)  # frame indices the capture loses
    fail_moves: set[int] = field(default_factory=set)  # move ids that time out
    plan: tuple[int, int, int] | None = PLAN
    sigma: float | None = None
    # σ the core reports once a burst has closed (its first depth); None: ``sigma`` throughout.
    sigma_after_burst: float | None = None
    centroid: tuple[float, float] | None = None
    phase: float = 0.0123  # exposure mid of frame 0

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)
        self.sched = Scheduler(self.config)
        self.motor = Motor([(0.0, 5000.0, 0.0, 5000.0)])
        self.events: list[tuple[float, int, str, object]] = []
        self.seq = 0
        self.tags: list[tuple[int, float, FrameTag]] = []
        self.actions: list[tuple[float, object]] = []
        self.wrong: list[str] = []
        self.now = 0.0
        self.period = 1.0 / self.config.fps
        self.half = self.config.exposure / 2.0
        self.next_index = 0

    def push(self, t: float, kind: str, data: object = None) -> None:
        self.seq += 1
        heapq.heappush(self.events, (t, self.seq, kind, data))

    def run(self, seconds: float) -> None:
        latency = self.config.capture_latency_frames * self.period
        first = max(self.next_index, math.ceil((self.now - self.phase) / self.period))
        n = int(seconds * self.config.fps)
        self.next_index = first + n
        for i in range(first, first + n):
            mid = self.phase + i * self.period
            if i not in self.drop:
                self.push(mid + self.half + latency + 0.001, "frame", (i, mid))
        end = self.phase + (first + n) * self.period + latency + 0.2
        self.step(self.now)
        while self.events and self.events[0][0] < end:
            t, _, kind, data = heapq.heappop(self.events)
            assert t >= self.now - 1e-12
            self.now = t
            self.handle(kind, data)
            self.step(t)

    def step(self, now: float) -> None:
        for action in self.sched.next_actions(now):
            self.actions.append((now, action))
            self.execute(now, action)
        wake = self.sched.next_wakeup()
        if wake is not None:
            # The scheduler must never ask to be woken in the past after acting (busy loop).
            assert wake > now, (wake, now, self.sched.phase)
            if wake < now + 10.0:
                self.push(wake, "wake")

    def execute(self, now: float, action: object) -> None:
        cfg = self.config
        if isinstance(action, FocusMove):
            start = now + link_time_s(9, cfg.baudrate) + self.rng.uniform(0, cfg.command_slot_s)
            here = self.motor.position(start)
            end = start + abs(action.counts - here) / cfg.focus_speed_counts_per_s
            if action.move_id in self.fail_moves:
                # The motor moves but the Completion is lost; the shell times out later.
                self.motor.segments.append((start, here, end, float(action.counts)))
                self.push(end + 0.2, "focus_failed", action.move_id)
                return
            self.motor.segments.append((start, here, end, float(action.counts)))
            self.push(end + link_time_s(3, cfg.baudrate), "focus_done", action.move_id)
        elif isinstance(action, FocusInquiry):
            self.push(now + 0.01, "focus_pos", round(self.motor.position(now + 0.005)))
        elif isinstance(action, PanTiltInquiry):
            self.push(now + 0.02, "pt_pos")
        elif isinstance(action, PanTiltDrive | PanTiltAbsolute | PanTiltStop):
            self.push(now + 0.02, "pt_done")

    def handle(self, kind: str, data: object) -> None:
        s = self.sched
        if kind == "frame":
            assert isinstance(data, tuple)
            index, mid = data
            t = mid + self.rng.uniform(-self.jitter_s, self.jitter_s)
            tag = s.on_frame(index, t)
            self.tags.append((index, mid, tag))
            self.check(index, mid, tag)
            counts = tag.focus_counts if tag.focus_counts is not None else 5000
            plan = self.plan
            if self.sigma_after_burst is not None and s.stats.bursts_completed > 0:
                self.sigma = self.sigma_after_burst
            s.on_estimate(
                t,
                sigma_m=self.sigma,
                plan=plan,
                centroid_px=self.centroid,
                pan_deg=tag.pan_deg,
                tilt_deg=tag.tilt_deg,
            )
            del counts
        elif kind == "focus_done":
            assert isinstance(data, int)
            s.on_focus_completed(data, self.now)
        elif kind == "focus_failed":
            assert isinstance(data, int)
            s.on_focus_failed(data, self.now)
        elif kind == "focus_pos":
            assert isinstance(data, int)
            s.on_focus_position(self.now, data)
        elif kind == "pt_pos":
            s.on_pan_tilt_position(self.now, 0.0, 0.0)
        elif kind == "pt_done":
            s.on_pan_tilt_done(self.now)

    def check(self, index: int, mid: float, tag: FrameTag) -> None:
        a, b = mid - self.half, mid + self.half
        if tag.role == "transit":
            if tag.focus_counts is not None:
                self.wrong.append(f"frame {index}: transit with counts")
            return
        if self.motor.moved_during(a, b):
            self.wrong.append(f"frame {index}: {tag.role} but the lens moved during exposure")
        true = self.motor.position(mid)
        if tag.focus_counts is None or abs(true - tag.focus_counts) > 0.5:
            self.wrong.append(f"frame {index}: tagged {tag.focus_counts}, lens at {true}")
        if (tag.role == "burst") != (tag.burst is not None):
            self.wrong.append(f"frame {index}: role {tag.role} with burst {tag.burst}")

    def bursts(self) -> dict[int, list[tuple[int, int]]]:
        out: dict[int, list[tuple[int, int]]] = {}
        for index, _, tag in self.tags:
            if tag.burst is not None:
                out.setdefault(tag.burst[0], []).append((tag.burst[1], index))
        return out

    def achieved_hz(self) -> float:
        done = sorted(
            max(i for _, i in slots) for slots in self.bursts().values() if len(slots) == 3
        )
        if len(done) < 3:
            return 0.0
        return (len(done) - 1) / ((done[-1] - done[0]) / self.config.fps)


# -- pure helpers ------------------------------------------------------------------------------
def test_link_and_move_times_follow_the_baud_rate() -> None:
    assert link_time_s(9, 9600) == pytest.approx(9 * 10 / 9600)
    assert focus_move_time_s(BASE, 0) == 0.0
    expected = 90 / 9600 + 1 / 60 + 400 / 20000 + 30 / 9600
    assert focus_move_time_s(BASE, 400) == pytest.approx(expected)
    assert focus_move_time_s(replace(BASE, baudrate=38400), 400) < expected


def test_rate_limit_by_hand() -> None:
    # E = 33.3 ms, guards 2×6 ms: a 300-count move takes 9.4+16.7+15+3.1 = 44.2 ms → 89.5 ms
    # wait → 3 periods; a 600-count move 59.2 ms → 104.5 ms → 4 periods; cycle 3+4+3+6 = 16.
    limit = depth_rate_limit(BASE, 300)
    assert limit.move_frames == (3, 4, 3)
    assert limit.cycle_frames == 16
    assert limit.depth_hz == pytest.approx(30 / 16)
    # Without prediction each move also waits for the claimed frame to be delivered.
    slow = depth_rate_limit(BASE, 300, predictive=False)
    assert slow.depth_hz < limit.depth_hz
    assert slow.move_frames == (5, 6, 5)
    # More tracking frames per burst, faster motor, higher baud rate: monotone effects.
    assert depth_rate_limit(replace(BASE, burst_every_frames=20), 300).depth_hz < limit.depth_hz
    fast = replace(BASE, focus_speed_counts_per_s=1e6, baudrate=115200, command_slot_s=0.001)
    assert depth_rate_limit(fast, 300).move_frames == (2, 2, 2)
    assert depth_rate_limit(BASE, 0).cycle_frames == 3 + BASE.burst_every_frames


def test_visca_speed_index_is_nearest_and_never_zero_for_motion() -> None:
    assert visca_speed_index(0.0, PAN) == 0
    assert visca_speed_index(0.01, PAN) == 1
    assert visca_speed_index(-0.01, PAN) == -1
    assert visca_speed_index(14.0, PAN) == 10
    assert visca_speed_index(-52.0, PAN) == -16
    assert visca_speed_index(1000.0, PAN) == 0x18
    assert visca_speed_index(1000.0, TILT) == 0x14
    assert speed_of_index(-10, PAN) == -14.0
    assert speed_of_index(0, PAN) == 0.0


def test_pixel_offset_to_angle() -> None:
    assert pixel_offset_to_deg(0.0, 4.0, 0.006) == 0.0
    # 100 px × 6 µm = 0.6 mm at f = 4 mm: atan(0.15)
    assert pixel_offset_to_deg(100.0, 4.0, 0.006) == pytest.approx(math.degrees(math.atan(0.15)))
    assert pixel_offset_to_deg(-100.0, 4.0, 0.006) < 0


def test_order_settings_minimises_travel() -> None:
    # Lens at the centre: take it first, then one side, the other, back to the centre.
    order = order_settings(5000, (4700, 5000, 5300), 5000, BASE)
    assert order[0] == 5000
    assert sorted(order) == [4700, 5000, 5300]
    # Lens far on one side, home in the middle: sweep monotonically from the near end.
    order = order_settings(4000, (4700, 5000, 5300), 5000, BASE)
    assert order[0] == 4700
    assert order[1] == 5000 or order == (4700, 5300, 5000)


def test_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="fps"):
        replace(BASE, fps=0)
    with pytest.raises(ValueError, match="exposure_s"):
        replace(BASE, fps=30, exposure_s=0.05)
    with pytest.raises(ValueError, match="burst_every_frames"):
        replace(BASE, burst_every_frames=-1)


# -- the scheduler against the model camera ----------------------------------------------------
def test_tags_are_truthful_and_bursts_reach_the_rate_limit() -> None:
    h = Harness(BASE)
    h.run(6.0)
    assert h.wrong == []
    bursts = h.bursts()
    complete = [b for b in bursts.values() if sorted(s for s, _ in b) == [0, 1, 2]]
    assert len(complete) >= 8
    # Each complete burst covers three distinct settings bracketing the plan.
    for burst_id, slots in bursts.items():
        if len(slots) == 3:
            counts = {h.tags[i][2].focus_counts for _, i in slots}
            assert counts == set(PLAN), burst_id
    limit = depth_rate_limit(BASE, 300).depth_hz
    assert h.achieved_hz() >= 0.9 * limit
    assert h.sched.stats.bursts_incomplete == 0
    # Tracking frames only at the tracking focus; transit frames exist (the lens does move).
    roles = h.sched.stats.frames
    assert roles["transit"] > 0
    # Tracking frames are at the tracking focus; an unclaimed frame between a burst's slots is
    # transit (a track tag would make the core end the burst early).
    assert all(tag.focus_counts == 5000 for _, _, tag in h.tags if tag.role == "track")
    for slots in bursts.values():
        indices = sorted(i for _, i in slots)
        between = [tag for i, _, tag in h.tags if indices[0] < i < indices[-1]]
        assert all(tag.role in ("burst", "transit") for tag in between)
    assert h.sched.achieved_rate_hz(h.now) == pytest.approx(h.achieved_hz(), rel=0.15)


def test_first_move_goes_to_the_initial_focus() -> None:
    h = Harness(replace(BASE, initial_focus_counts=6000), plan=None)
    h.run(1.0)
    moves = [a for _, a in h.actions if isinstance(a, FocusMove)]
    assert [m.counts for m in moves] == [6000]
    assert h.wrong == []
    late = [tag for _, mid, tag in h.tags if mid > 0.5]
    assert late
    assert all(tag.role == "track" and tag.focus_counts == 6000 for tag in late)


def test_no_plan_no_bursts() -> None:
    h = Harness(BASE, plan=None)
    h.run(2.0)
    assert h.sched.stats.bursts_started == 0
    assert not any(tag.role == "burst" for _, _, tag in h.tags)


@pytest.mark.parametrize("latency", [0, 1, 3, 5])
def test_latency_does_not_cost_rate_in_steady_state(latency: int) -> None:
    cfg = replace(BASE, capture_latency_frames=latency)
    h = Harness(cfg)
    h.run(5.0)
    assert h.wrong == []
    assert h.achieved_hz() >= 0.9 * depth_rate_limit(cfg, 300).depth_hz


def test_timestamp_jitter_within_margin_never_mis_tags() -> None:
    cfg = replace(BASE, timing_margin_s=0.004)
    h = Harness(cfg, jitter_s=0.002, seed=7)
    h.run(5.0)
    assert h.wrong == []
    assert h.sched.stats.bursts_completed >= 6


def test_dropped_claimed_frame_makes_an_incomplete_burst_and_work_goes_on() -> None:
    probe = Harness(BASE)
    probe.run(2.0)
    first_burst_frames = [i for i, _, tag in probe.tags if tag.burst == (2, 1)]
    assert first_burst_frames
    h = Harness(BASE, drop={first_burst_frames[0]})
    h.run(4.0)
    assert h.wrong == []
    assert h.sched.stats.bursts_incomplete == 1
    assert 2 not in {b for b, slots in h.bursts().items() if len(slots) == 3}
    assert h.sched.stats.bursts_completed >= 4


def test_failed_focus_move_is_recovered_by_inquiry() -> None:
    h = Harness(BASE, fail_moves={3})
    h.run(4.0)
    assert h.wrong == []
    assert h.sched.stats.focus_failures == 1
    assert h.sched.stats.focus_inquiries >= 2
    assert h.sched.stats.bursts_incomplete == 1
    # After recovery the scheduler returns to bursting.
    assert any(tag.role == "burst" for _, mid, tag in h.tags if mid > 2.0)


def test_unknown_initial_focus_is_inquired_until_two_readings_agree() -> None:
    h = Harness(replace(BASE, initial_focus_counts=None), plan=None)
    h.run(1.0)
    inquiries = [a for _, a in h.actions if isinstance(a, FocusInquiry)]
    assert len(inquiries) >= 2
    assert h.sched.focus_counts == 5000
    assert h.wrong == []
    assert h.tags[-1][2].role == "track"


def test_late_or_duplicate_completion_is_ignored() -> None:
    s = Scheduler(BASE)
    [move] = s.next_actions(0.0)
    assert isinstance(move, FocusMove)
    s.on_focus_completed(move.move_id + 7, 0.05)
    assert s.focus_counts is None
    s.on_focus_completed(move.move_id, 0.06)
    assert s.focus_counts == 5000
    s.on_focus_completed(move.move_id, 0.07)
    assert s.phase == "track"


def test_inquiry_equal_to_target_settles_an_outstanding_move() -> None:
    s = Scheduler(BASE)
    [move] = s.next_actions(0.0)
    assert isinstance(move, FocusMove)
    s.on_focus_position(0.03, 4990)
    assert s.focus_counts is None
    s.on_focus_position(0.05, 5000)
    assert s.focus_counts == 5000


def test_frames_before_any_focus_knowledge_are_transit() -> None:
    s = Scheduler(BASE)
    s.next_actions(0.0)
    tag = s.on_frame(0, 0.01)
    assert tag == FrameTag("transit", None, 0.0, 0.0)


def test_sigma_trigger_starts_bursts_sooner() -> None:
    cfg = replace(BASE, burst_every_frames=30, sigma_trigger_m=0.05)
    calm = Harness(cfg, sigma=0.01)
    calm.run(4.0)
    nervous = Harness(cfg, sigma=0.2)
    nervous.run(4.0)
    assert nervous.wrong == []
    assert nervous.sched.stats.bursts_completed > 2 * calm.sched.stats.bursts_completed


def test_request_burst_and_cancel() -> None:
    cfg = replace(BASE, burst_every_frames=1000)
    h = Harness(cfg)
    h.run(1.0)
    assert h.sched.stats.bursts_started == 0
    h.sched.request_burst()
    h.sched.cancel_bursts()
    h.plan = None
    h.run(1.0)
    assert h.sched.stats.bursts_started == 0


def test_moving_plan_retargets_the_tracking_focus() -> None:
    h = Harness(BASE, plan=(5700, 6000, 6300))
    h.run(2.0)
    assert h.wrong == []
    assert h.sched.track_counts == 6000
    late = [tag.focus_counts for _, mid, tag in h.tags if mid > 1.0 and tag.role == "track"]
    assert late
    assert late.count(6000) >= 0.9 * len(late)
    assert 5000 not in late


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    fps=st.sampled_from([15.0, 25.0, 30.0, 60.0]),
    latency=st.integers(0, 4),
    every=st.integers(0, 12),
    speed=st.sampled_from([5000.0, 20000.0, 80000.0]),
    exposure_fraction=st.sampled_from([0.3, 0.7, 1.0]),
    spacing=st.sampled_from([50, 300, 900]),
    seed=st.integers(0, 1000),
)
def test_property_tags_truthful_and_rate_near_limit(
    fps: float,
    latency: int,
    every: int,
    speed: float,
    exposure_fraction: float,
    spacing: int,
    seed: int,
) -> None:
    cfg = replace(
        BASE,
        fps=fps,
        capture_latency_frames=latency,
        burst_every_frames=every,
        focus_speed_counts_per_s=speed,
        exposure_s=exposure_fraction / fps,
        snap_counts=min(40, spacing // 3),
    )
    plan = (5000 - spacing, 5000, 5000 + spacing)
    limit = depth_rate_limit(cfg, spacing).depth_hz
    h = Harness(cfg, plan=plan, seed=seed)
    h.run(max(3.0, 6.0 / limit))  # at least ~5 complete bursts
    assert h.wrong == []
    assert h.achieved_hz() >= 0.9 * limit


# -- pan/tilt ----------------------------------------------------------------------------------
PT = replace(
    BASE,
    pan_tilt_mode="drive",
    focal_length_mm=4.0,
    pixel_pitch_mm=0.006,
    frame_size=(640, 480),
    pan_tilt_poll_interval_s=0.25,
)


def _pan_tilt_commands(h: Harness) -> list[tuple[float, object]]:
    return [
        (t, a) for t, a in h.actions if isinstance(a, PanTiltDrive | PanTiltAbsolute | PanTiltStop)
    ]


def test_target_right_and_up_drives_pan_right_and_tilt_up() -> None:
    h = Harness(PT, centroid=(600.0, 40.0))
    h.run(0.5)
    cmds = _pan_tilt_commands(h)
    assert cmds
    first = cmds[0][1]
    assert isinstance(first, PanTiltDrive)
    assert first.pan_speed > 0
    assert first.tilt_speed > 0
    assert first.pan_rate_deg_s == speed_of_index(first.pan_speed, PAN)


def test_centred_target_gives_no_motion_and_lost_target_is_searched_for() -> None:
    h = Harness(PT, centroid=(319.5, 239.5))
    h.run(0.5)
    assert _pan_tilt_commands(h) == []
    cfg = replace(PT, pan_tilt_lost_s=0.5, pan_tilt_search_s=1.0)
    h2 = Harness(cfg, centroid=(600.0, 239.5))
    h2.run(0.3)
    assert isinstance(_pan_tilt_commands(h2)[-1][1], PanTiltDrive)
    lost_at = h2.now
    h2.centroid = None
    h2.run(2.5)
    cmds = [(t, a) for t, a in _pan_tilt_commands(h2) if t > lost_at]
    # Lost: no stop, but a bounded search, then one absolute move back to the last direction.
    assert not any(isinstance(a, PanTiltStop) for _, a in cmds)
    returns = [(t, a) for t, a in cmds if isinstance(a, PanTiltAbsolute)]
    assert len(returns) == 1
    t_ret, ret = returns[0]
    assert t_ret - lost_at >= cfg.pan_tilt_lost_s + cfg.pan_tilt_search_s - 0.1
    expected = pixel_offset_to_deg(600.0 - 319.5, cfg.focal_length_mm, cfg.pixel_pitch_mm)
    # The harness answers pan 0 to every inquiry while the head drives: the model stays within
    # a count plus one field of motion of such a reading (it is not snapped to it).
    assert ret.pan_deg == pytest.approx(expected, abs=1.0)
    assert cmds[-1][1] is ret  # then it holds there
    assert h2.sched.searching is False


def test_release_stops_pan_tilt_once_without_search() -> None:
    h = Harness(PT, centroid=(600.0, 239.5))
    h.run(0.3)
    h.sched.stop_pan_tilt()
    h.centroid = None
    t0 = h.now
    h.run(3.0)
    cmds = [a for t, a in _pan_tilt_commands(h) if t >= t0]
    assert cmds == [PanTiltStop()]


def test_feedforward_from_the_first_two_centroids() -> None:
    """A target crossing at 7°/s is followed at 7°/s from its second centroid on."""
    cfg = replace(PT, focal_length_mm=31.0, pixel_pitch_mm=0.005, pan_tilt_poll_interval_s=100.0)
    s = Scheduler(cfg)
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    s.on_pan_tilt_done(0.0)
    px_per_deg = 1.0 / pixel_offset_to_deg(1.0, 31.0, 0.005)
    for k in range(2):
        t = 0.1 + k / 30.0
        s.on_estimate(
            t, sigma_m=None, plan=None, centroid_px=(319.5 + 7.0 * t * px_per_deg, 239.5),
            pan_deg=0.0, tilt_deg=0.0,
        )  # fmt: skip
    drives = [a for a in s.next_actions(0.2) if isinstance(a, PanTiltDrive)]
    assert len(drives) == 1
    assert drives[0].pan_rate_deg_s >= 7.0


@pytest.mark.parametrize("use_track", [False, True])
def test_feedforward_from_the_3d_tracker_when_switched_on(use_track: bool) -> None:
    """A still centroid but a tracker saying 7°/s: the head runs 7°/s only with the switch on."""
    cfg = replace(
        PT,
        focal_length_mm=31.0,
        pixel_pitch_mm=0.005,
        pan_tilt_poll_interval_s=100.0,
        pan_tilt_track_feedforward=use_track,
    )
    s = Scheduler(cfg)
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    s.on_pan_tilt_done(0.0)
    for k in range(3):
        s.on_estimate(
            0.1 + k / 30.0, sigma_m=None, plan=None, centroid_px=(319.5, 239.5),
            pan_deg=0.0, tilt_deg=0.0, track_rate_deg_s=(7.0, 0.0),
        )  # fmt: skip
    drives = [a for a in s.next_actions(0.2) if isinstance(a, PanTiltDrive)]
    if use_track:
        assert len(drives) == 1
        assert drives[0].pan_rate_deg_s >= 7.0
        assert drives[0].tilt_speed == 0
    else:
        assert drives == []  # the centroid does not move: nothing to follow


def test_bursts_wait_for_a_stable_contour() -> None:
    cfg = replace(BASE, acquire_stable_frames=3)
    h = Harness(cfg, centroid=None)
    h.run(1.5)
    assert h.sched.stats.bursts_started == 0  # plans without a contour are not followed
    h.centroid = (319.5, 239.5)
    h.run(1.5)
    assert h.sched.stats.bursts_started >= 2


def test_pan_tilt_command_rate_and_link_budget() -> None:
    cfg = replace(PT, pan_tilt_min_interval_s=0.1, pan_tilt_gain_per_s=3.0)
    h = Harness(cfg, centroid=(600.0, 400.0))
    # A target that keeps moving in the image so the controller keeps changing its command.
    h.run(3.0)
    cmds = _pan_tilt_commands(h)
    times = [t for t, _ in cmds]
    assert all(b - a >= 0.1 - 1e-9 for a, b in itertools.pairwise(times))
    focus_times = [t for t, a in h.actions if isinstance(a, FocusMove)]
    pt_times = [t for t, a in h.actions if isinstance(a, (*PT_CMDS, PanTiltInquiry))]
    for ft in focus_times:
        assert all(not (0 <= pt - ft < cfg.command_slot_s - 1e-6) for pt in pt_times)
    # Focus and pan/tilt both keep working (two sockets): bursts still complete.
    assert h.wrong == []
    assert h.sched.stats.bursts_completed >= 4
    assert any(isinstance(a, PanTiltInquiry) for _, a in h.actions)


PT_CMDS = (PanTiltDrive, PanTiltAbsolute, PanTiltStop)


def test_error_is_corrected_for_camera_motion_since_exposure() -> None:
    s = Scheduler(replace(PT, pan_tilt_poll_interval_s=100.0))
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    # Target 5° right at exposure t=1.0 while the camera was at pan 0 …
    offset_px = math.tan(math.radians(5.0)) * 4.0 / 0.006
    s.on_estimate(
        1.0,
        sigma_m=None,
        plan=None,
        centroid_px=(319.5 + offset_px, 239.5),
        pan_deg=0.0,
        tilt_deg=0.0,
    )
    # … but the camera is already at 5° now: no command.
    s.on_pan_tilt_position(1.05, 5.0, 0.0)
    assert [a for a in s.next_actions(1.1) if isinstance(a, PT_CMDS)] == []


def test_absolute_mode_targets_the_target_direction() -> None:
    s = Scheduler(replace(PT, pan_tilt_mode="absolute", pan_tilt_poll_interval_s=100.0))
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 10.0, -2.0)
    offset_px = math.tan(math.radians(3.0)) * 4.0 / 0.006
    s.on_estimate(
        0.5,
        sigma_m=None,
        plan=None,
        centroid_px=(319.5 - offset_px, 239.5),
        pan_deg=10.0,
        tilt_deg=-2.0,
    )
    cmds = [a for a in s.next_actions(0.6) if isinstance(a, PanTiltAbsolute)]
    assert len(cmds) == 1
    assert cmds[0].pan_deg == pytest.approx(7.0)
    assert cmds[0].tilt_deg == pytest.approx(-2.0)
    # The same goal is not re-sent.
    s.on_pan_tilt_done(0.62)
    s.on_estimate(
        0.7,
        sigma_m=None,
        plan=None,
        centroid_px=(319.5 - offset_px, 239.5),
        pan_deg=10.0,
        tilt_deg=-2.0,
    )
    assert [a for a in s.next_actions(0.8) if isinstance(a, PanTiltAbsolute)] == []


def test_pan_tilt_model_dead_reckons_between_inquiries() -> None:
    s = Scheduler(replace(PT, pan_tilt_poll_interval_s=100.0))
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    s.on_estimate(0.2, sigma_m=None, plan=None, centroid_px=(639.0, 239.5))
    [drive] = [a for a in s.next_actions(0.3) if isinstance(a, PanTiltDrive)]
    s.on_pan_tilt_done(0.32)
    pan, tilt = s.pan_tilt_at(1.3)
    # The motors change when the camera takes the command: its bytes plus half a field on average.
    delay = s.config.pan_tilt_model_delay_s
    assert pan == pytest.approx(drive.pan_rate_deg_s * (1.0 - delay))
    assert s.pan_tilt_at(0.3 + delay / 2.0) == (0.0, 0.0)  # not yet moving
    assert tilt == 0.0
    # A frame is tagged with the modelled pan at its exposure.
    tag = s.on_frame(0, 1.3)
    assert tag.pan_deg == pytest.approx(pan)


def test_pan_tilt_off_issues_nothing() -> None:
    h = Harness(BASE, centroid=(600.0, 40.0))
    h.run(0.5)
    assert not any(isinstance(a, (*PT_CMDS, PanTiltInquiry)) for _, a in h.actions)


def test_set_policy_changes_the_burst_interval_at_run_time() -> None:
    h = Harness(replace(BASE, burst_every_frames=1000))
    h.run(1.0)
    assert h.sched.stats.bursts_started == 0
    h.sched.set_policy(4, None)
    h.run(2.0)
    assert h.wrong == []
    assert h.sched.stats.bursts_completed >= 3


def test_feedforward_follows_a_moving_target_and_missing_centroids_do_not_stop() -> None:
    s = Scheduler(replace(PT, pan_tilt_poll_interval_s=100.0, pan_tilt_gain_per_s=0.5))
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    px_per_deg = 4.0 / 0.006 * math.radians(1.0)
    # The target crosses the (fixed) image at 10°/s; centroids every 1/30 s.
    for k in range(10):
        t = 0.5 + k / 30
        s.on_estimate(
            t,
            sigma_m=None,
            plan=None,
            centroid_px=(319.5 + 10.0 * (t - 0.5) * px_per_deg, 239.5),
            pan_deg=0.0,
            tilt_deg=0.0,
        )
    drives = [a for a in s.next_actions(0.9) if isinstance(a, PanTiltDrive)]
    assert drives
    # Feed-forward: about the target's 10°/s even with a small proportional gain.
    assert 7.0 <= drives[0].pan_rate_deg_s <= 14.0
    s.on_pan_tilt_done(0.91)
    # One frame without a contour does not stop the head …
    s.on_estimate(0.95, sigma_m=None, plan=None, centroid_px=None)
    assert not any(isinstance(a, PanTiltStop) for a in s.next_actions(1.05))
    s.on_pan_tilt_done(1.06)
    # … nor does a target gone for longer than pan_tilt_lost_s: the head searches along the
    # predicted path (still about 10°/s), then returns to the last direction seen.
    s.on_estimate(1.6, sigma_m=None, plan=None, centroid_px=None)
    assert s.searching
    assert not any(isinstance(a, PanTiltStop) for a in s.next_actions(1.7))
    late = 0.5 + 9 / 30 + s.config.pan_tilt_lost_s + s.config.pan_tilt_search_s + 0.1
    s.on_estimate(late, sigma_m=None, plan=None, centroid_px=None)
    back = [a for a in s.next_actions(late + 0.1) if isinstance(a, PanTiltAbsolute)]
    assert len(back) == 1
    assert back[0].pan_deg == pytest.approx(10.0 * 9 / 30, abs=0.3)


# -- rolling bracket ---------------------------------------------------------------------------
ROLL = replace(BASE, burst_mode="rolling", burst_every_frames=1, exposure_s=0.004)


def test_rolling_rate_limit_by_hand() -> None:
    # E = 4 ms, guards 2×6 ms: a 3000-count move takes 9.4+16.7+150+3.1 = 179.2 ms → 195.2 ms
    # → 6 periods; mid → end → mid with one tracking frame: 12 frames a depth.
    limit = depth_rate_limit(ROLL, 3000)
    assert limit.move_frames == (6, 6)
    assert limit.cycle_frames == 12
    assert limit.depth_hz == pytest.approx(2.5)
    assert depth_rate_limit(replace(ROLL, burst_every_frames=3), 3000).cycle_frames == 14
    # The classic burst at the same spacing: mid → end → end → mid (6+11+6) + its track frames.
    classic = depth_rate_limit(replace(ROLL, burst_mode="classic"), 3000)
    assert classic.cycle_frames == 6 + 11 + 6 + 1


def test_rate_limit_of_a_bracket_with_unequal_sides() -> None:
    # Brackets symmetric in v are not in counts: each side's move costs its own frames. A
    # 3500-count move: 9.4+16.7+175+3.1 ms + 16 ms of exposure and guards → 7 periods.
    assert depth_rate_limit(ROLL, (3000, 3000)) == depth_rate_limit(ROLL, 3000)
    limit = depth_rate_limit(ROLL, (3000, 3500))
    assert limit.move_frames == (6, 7)
    assert limit.cycle_frames == 13  # one end and back per depth: 6 and 7 on average
    classic = depth_rate_limit(replace(ROLL, burst_mode="classic"), (3000, 3500))
    assert classic.move_frames == (6, 12, 7)


@pytest.mark.parametrize("every", [1, 2, 4])
def test_rolling_tags_alternate_ends_and_reach_the_rate_limit(every: int) -> None:
    # The steady state: a depth known from the start (the start-up is tested below).
    cfg = replace(ROLL, burst_every_frames=every)
    plan = (2000, 5000, 8000)
    h = Harness(cfg, plan=plan, sigma=0.01)
    h.run(5.0)
    assert h.wrong == []
    ends = [(index, tag) for index, _, tag in h.tags if tag.role == "burst"]
    assert len(ends) >= 10
    assert all(tag.burst is not None and tag.burst[1] == 2 for _, tag in ends)
    counts = [tag.focus_counts for _, tag in ends]
    assert all(c in (2000, 8000) for c in counts)
    assert all(a != b for a, b in itertools.pairwise(counts))  # alternating sides
    # Between consecutive ends: exactly ``every`` tracking frames at the middle, the rest transit.
    for (i0, _), (i1, _) in itertools.pairwise(ends):
        between = [tag for i, _, tag in h.tags if i0 < i < i1]
        track = [tag for tag in between if tag.role == "track"]
        assert len(track) == every
        assert all(tag.focus_counts == 5000 for tag in track)
    stats = h.sched.stats
    assert stats.rolling_openings == 1
    assert stats.bursts_completed == len(ends) - 1
    span_s = (ends[-1][0] - ends[0][0]) / cfg.fps
    achieved = (len(ends) - 1) / span_s
    assert achieved >= 0.9 * depth_rate_limit(cfg, 3000).depth_hz


def test_rolling_plan_survives_transit_frames_and_end_uses_the_latest_plan() -> None:
    # Transit frames bring no plan from the core (it plans from a known focus): the last plan
    # stays, so the middle frame is claimed at once after the lens settles.
    h = Harness(replace(ROLL, capture_latency_frames=1), plan=(2000, 5000, 8000))
    h.run(2.0)
    h.plan = (2500, 5500, 8500)
    h.run(2.0)
    late = [tag.focus_counts for _, mid, tag in h.tags if tag.role == "burst" and mid > 2.8]
    assert late
    assert set(late) <= {2500, 8500}
    assert h.wrong == []


def _measured(h: Harness) -> list[tuple[int, float, FrameTag]]:
    """The frames at a known focus away from the initial one, in order."""
    return [
        (index, mid, tag)
        for index, mid, tag in h.tags
        if tag.role in ("burst", "track") and tag.focus_counts != ROLL.initial_focus_counts
    ]


@pytest.mark.parametrize("far_side", [-1, 1])
def test_the_first_bracket_runs_from_its_near_end_to_its_far_end_and_holds_there(
    far_side: int,
) -> None:
    # No depth yet (σ unknown) and the lens away from the plan: straight to the near end, one
    # frame at the middle, then the far end — and the lens stays there for the frame that closes
    # the burst in the core, until the core's feedback on it is in.
    cfg = replace(ROLL, far_focus_side=far_side)
    near, far = (12000, 6000) if far_side < 0 else (6000, 12000)
    h = Harness(cfg, plan=(6000, 9000, 12000), sigma_after_burst=0.2)
    h.run(3.0)
    assert h.wrong == []
    measured = _measured(h)
    ends = [(i, tag.focus_counts) for i, _, tag in measured if tag.role == "burst"]
    assert [c for _, c in ends[:3]] == [near, far, near]
    first, second = ends[0][0], ends[1][0]
    middles = [i for i, _, tag in measured if first < i < second]
    assert middles == [middles[0]]  # one middle frame before the first depth
    assert measured[[i for i, _, _ in measured].index(middles[0])][2].focus_counts == 9000
    # The frames after the far end are tracking frames there (the first closes the burst in the
    # core), and the lens leaves only once the first of them has been delivered and fed back.
    after = [(i, mid, tag) for i, mid, tag in h.tags if second < i <= second + 2]
    assert [(tag.role, tag.focus_counts) for _, _, tag in after] == [("track", far)] * 2
    delivered = after[0][1] + cfg.exposure / 2 + cfg.capture_latency_frames / cfg.fps
    leave = next(t for t, a in h.actions if isinstance(a, FocusMove) and t > after[0][1])
    assert leave >= delivered
    # The lens holds at the first closing end after the depth too (the first depth of a far
    # target), not at later ones (the rolling triangle goes on).
    tags = {i: tag for i, _, tag in h.tags}
    far_ends = [i for i, c in ends if c == far]
    assert len(far_ends) >= 3
    held = [(tags[i + 1].role, tags[i + 1].focus_counts) == ("track", far) for i in far_ends]
    assert held[:3] == [True, True, False]
    assert h.sched.stats.bursts_completed >= 2


def test_a_start_up_bracket_without_a_depth_opens_again_where_the_lens_holds() -> None:
    # The first burst gave no depth (σ still unknown): the next sequence opens at the far end
    # where the lens already is — no move, the frame after the hold is claimed there.
    h = Harness(ROLL, plan=(6000, 9000, 12000))
    h.run(2.5)
    assert h.wrong == []
    ends = [tag.focus_counts for _, _, tag in _measured(h) if tag.role == "burst"]
    assert ends[:4] == [12000, 6000, 6000, 12000]
    moves = [a.counts for _, a in h.actions if isinstance(a, FocusMove)]
    assert moves[:5] == [5000, 12000, 9000, 6000, 9000]


def test_a_hold_without_feedback_ends_by_its_deadline() -> None:
    # The capture loses every frame after the far end: no feedback ever comes, yet the hold ends
    # by its deadline (the scheduler asks to be woken for it) and the lens goes on.
    h = Harness(ROLL, plan=(6000, 9000, 12000), drop=set(range(27, 1000)))
    h.run(2.0)
    assert h.wrong == []
    far = [mid for _, mid, tag in h.tags if tag.role == "burst" and tag.focus_counts == 6000]
    assert len(far) == 1
    later = [(t, a.counts) for t, a in h.actions if isinstance(a, FocusMove) and t > far[0]]
    assert later
    t_next, _ = later[0]
    latency = (ROLL.capture_latency_frames + 4) / ROLL.fps + ROLL.exposure
    assert t_next <= far[0] + latency + 0.01


def test_with_a_depth_a_retarget_refocuses_the_middle_first() -> None:
    # σ known: the burst policy decides when to burst; a far plan only re-focuses the lens.
    h = Harness(replace(ROLL, burst_every_frames=4), plan=(6000, 9000, 12000), sigma=0.01)
    h.run(2.0)
    assert h.wrong == []
    first = next(
        tag
        for _, _, tag in h.tags
        if tag.role in ("burst", "track") and tag.focus_counts != ROLL.initial_focus_counts
    )
    assert (first.role, first.focus_counts) == ("track", 9000)


@dataclass
class _JumpHarness(Harness):
    """Moves the plan far away while the next rolling end is committed but not yet moved to
    (the live case: the plan comes with the frame the end was committed at)."""

    jump: tuple[int, int, int] = (12000, 15000, 18000)
    jumped_at: float | None = None

    def step(self, now: float) -> None:
        super().step(now)
        if self.jumped_at is None and now > 1.0 and self.sched.phase == "burst_wait":
            self.plan = self.jump
            self.jumped_at = now


def test_a_rolling_end_is_never_taken_across_a_plan_jump() -> None:
    # The lens re-focuses the new middle before any end, and the next end lies on the same
    # side of that middle as the last end, so the core opens a sequence instead of fitting a
    # bracket of the old end, the old middle and a new end.
    h = _JumpHarness(ROLL, plan=(2000, 5000, 8000), sigma=0.5)
    h.run(3.0)
    assert h.wrong == []
    assert h.jumped_at is not None
    last_end = [
        tag.focus_counts for _, mid, tag in h.tags if tag.role == "burst" and mid < h.jumped_at
    ][-1]
    assert last_end is not None
    assert last_end < 15000
    new = [
        tag
        for _, mid, tag in h.tags
        if mid > h.jumped_at
        and tag.role != "transit"
        and tag.focus_counts not in (2000, 5000, 8000)
    ]
    assert (new[0].role, new[0].focus_counts) == ("track", 15000)
    ends = [tag.focus_counts for tag in new if tag.role == "burst"]
    assert ends[:3] == [12000, 18000, 12000]  # the first below the middle, as the last end


# -- closed loop: a modelled head and a target at a constant angular velocity ------------------
FIELD_S = 1.0 / 60.0
TELE = replace(
    PT,
    focal_length_mm=31.0,
    pixel_pitch_mm=0.005,
    exposure_s=0.004,
    burst_mode="rolling",
    burst_every_frames=2,
    pan_tilt_deadband_deg=pixel_offset_to_deg(16.0, 31.0, 0.005),
)
WIDE_PLAN = (2000, 5000, 8000)  # half-bracket moves of ~0.15 s: the focus transits


@dataclass
class HeadHarness(Harness):
    """The harness with a pan axis that obeys Pan-tiltDrive at field boundaries (after the
    command's bytes) and a target moving at ``omega`` deg/s from ``start_deg``."""

    omega: float = 0.0
    start_deg: float = 0.0
    segments: list[tuple[float, float, float]] = field(default_factory=list)  # t0, pan0, rate

    def head(self, t: float) -> tuple[float, float]:
        """Pan (deg) and its rate at ``t``."""
        pan, rate, t_prev = 0.0, 0.0, 0.0
        for t0, pan0, r in self.segments:
            if t0 > t:
                break
            pan, rate, t_prev = pan0, r, t0
        return pan + rate * (t - t_prev), rate

    def execute(self, now: float, action: object) -> None:
        if isinstance(action, PanTiltDrive | PanTiltStop):
            rate = action.pan_rate_deg_s if isinstance(action, PanTiltDrive) else 0.0
            arrive = now + link_time_s(9, self.config.baudrate)
            t_eff = math.ceil(arrive / FIELD_S) * FIELD_S
            self.segments.append((t_eff, self.head(t_eff)[0], rate))
            self.push(t_eff + link_time_s(6, self.config.baudrate), "pt_done")
            return
        if isinstance(action, PanTiltInquiry):
            t_s = math.ceil(now / FIELD_S) * FIELD_S
            counts = round(self.head(t_s)[0] * 14.4)  # the head's resolution (EVI-D100)
            self.push(t_s + link_time_s(11, self.config.baudrate), "pt_pos", counts / 14.4)
            return
        super().execute(now, action)

    def handle(self, kind: str, data: object) -> None:
        if kind == "frame":
            assert isinstance(data, tuple)
            _, mid = data
            off = self.start_deg + self.omega * mid - self.head(mid)[0]
            px = math.tan(math.radians(off)) * self.config.focal_length_mm
            self.centroid = (319.5 + px / self.config.pixel_pitch_mm, 239.5)
        if kind == "pt_pos":
            assert isinstance(data, float)
            self.sched.on_pan_tilt_position(self.now, data, 0.0)
            return
        super().handle(kind, data)

    def measured_rates(self, after: float) -> list[float]:
        """Head pan rate at the start and end of every track/burst exposure after ``after``."""
        out = []
        for _, mid, tag in self.tags:
            if tag.role != "transit" and mid > after:
                out += [self.head(mid - self.half)[1], self.head(mid + self.half)[1]]
        return out

    def error_px(self, t: float) -> float:
        off = self.start_deg + self.omega * t - self.head(t)[0]
        return (
            math.tan(math.radians(off)) * self.config.focal_length_mm / self.config.pixel_pitch_mm
        )


@pytest.mark.parametrize("omega", [0.0, 0.6, -1.3, 2.7])
def test_head_follows_without_hunting_and_holds_speed_through_measured_frames(
    omega: float,
) -> None:
    h = HeadHarness(TELE, plan=WIDE_PLAN, omega=omega, start_deg=0.3)
    h.run(8.0)
    assert h.wrong == []
    assert h.sched.stats.bursts_completed >= 10  # corrections do not cost the focus its bursts
    # Measured exposures all see one speed, the table speed nearest the target's (0 below 1°/s):
    # no head-induced smear beyond |that speed − ω| × exposure, the same on every burst frame.
    quiet = set(h.measured_rates(after=2.0))
    nearest = speed_of_index(nearest_speed_index(omega, PAN), PAN)
    assert quiet == {nearest}
    # Centred within the band plus the drift of one rolling cycle, and no hunting: the head
    # never turns against the target.
    errors = [abs(h.error_px(2.0 + k * 0.01)) for k in range(600)]
    assert max(errors) <= 40.0
    rates = [r for t0, _, r in h.segments if t0 > 2.0]
    assert all(r * omega >= 0.0 for r in rates)
    # Rate limit and link budget held.
    times = [t for t, _ in _pan_tilt_commands(h)]
    assert all(b - a >= TELE.pan_tilt_min_interval_s - 1e-9 for a, b in itertools.pairwise(times))
    focus_times = [t for t, a in h.actions if isinstance(a, FocusMove)]
    assert all(
        not (0 <= pt - ft < TELE.command_slot_s - 1e-6) for pt in times for ft in focus_times
    )


def test_static_target_inside_the_band_gets_no_command() -> None:
    h = HeadHarness(TELE, plan=WIDE_PLAN, start_deg=pixel_offset_to_deg(10.0, 31.0, 0.005))
    h.run(3.0)
    assert _pan_tilt_commands(h) == []
    # Outside the band: pulses towards the target within the tracker's speed cap, then at rest.
    h2 = HeadHarness(TELE, plan=WIDE_PLAN, start_deg=pixel_offset_to_deg(60.0, 31.0, 0.005))
    h2.run(4.0)
    cmds = _pan_tilt_commands(h2)
    assert 2 <= len(cmds) <= 6
    drives = [a for _, a in cmds if isinstance(a, PanTiltDrive)]
    assert all(0.0 < a.pan_rate_deg_s <= TELE.pan_tilt_max_correction_deg_s for a in drives)
    assert abs(h2.error_px(4.0)) <= 16.0
    assert h2.head(4.0)[1] == 0.0


def test_no_target_velocity_from_directions_measured_mid_absolute_move() -> None:
    """The model runs an absolute move at constant speed while the motors accelerate and brake:
    directions measured mid-move are off, and two of them 1/30 s apart make a velocity of tens
    of °/s (seen: −2.9°/s made of a target crossing at +10°/s; the drive that followed ran the
    other way and lost it). The direction is kept; the velocity waits for a head at rest."""
    cfg = replace(PT, pan_tilt_poll_interval_s=100.0, pan_tilt_lost_s=0.2, pan_tilt_search_s=0.3)
    s = Scheduler(cfg)
    s.next_actions(0.0)
    s.on_pan_tilt_position(0.0, 0.0, 0.0)
    s.on_pan_tilt_done(0.0)

    def seen(t: float, real_pan: float) -> None:
        # A static target at pan 20°, imaged from the head's real pan, tagged with the model's.
        offset = math.tan(math.radians(20.0 - real_pan)) * 4.0 / 0.006
        model_pan, model_tilt = s.pan_tilt_at(t)
        s.on_estimate(
            t,
            sigma_m=None,
            plan=None,
            centroid_px=(319.5 + offset, 239.5),
            pan_deg=model_pan,
            tilt_deg=model_tilt,
        )

    seen(0.5, 0.0)
    # Seen once, then lost: after the bounded search the head returns to it in one absolute move.
    s.next_actions(0.5)
    s.on_pan_tilt_done(0.55)
    s.on_estimate(1.1, sigma_m=None, plan=None, centroid_px=None)
    [back] = [a for a in s.next_actions(1.1) if isinstance(a, PanTiltAbsolute)]
    assert back.pan_deg == pytest.approx(20.0, abs=0.01)
    # Seen again mid-move, the real head lagging the model by 1.0°, then by 0.5°.
    t1, t2 = 1.1 + 1 / 30, 1.1 + 2 / 30
    assert 0.0 < s.pan_tilt_at(t2)[0] < 20.0 - 1.0  # the model is still on its way
    seen(t1, s.pan_tilt_at(t1)[0] - 1.0)
    seen(t2, s.pan_tilt_at(t2)[0] - 0.5)
    s.on_pan_tilt_done(t2 + 0.01)
    t3 = t2 + 0.55  # further than MAX_VELOCITY_GAP_S: no velocity from t2 to t3 either
    assert s.pan_tilt_at(t3)[0] == back.pan_deg  # arrived
    seen(t3, back.pan_deg)
    # A velocity made of the slewing frames (−15°/s) would be fed forward as a drive now.
    drives = [a for a in s.next_actions(t3 + 0.05) if isinstance(a, PanTiltDrive)]
    assert drives == []
