"""FAST mode: simulator, scheduler and estimation core in lock-step *virtual* time.

A discrete-event loop over one virtual clock (injected into the simulator's
:class:`~drivers.sim.state.CameraState`). Events, in time order:

* the simulated VISCA device (:class:`drivers.sim.device.ViscaDevice`, wire pacing at 9600 baud,
  one message per video field, motors at their simulated speeds) emits replies, matched by the
  service's own VISCA session (:class:`drivers.sim.virtual_bus.VirtualBus`) → the
  :class:`~dffd.scheduler.Scheduler` hears Completions and positions when they would arrive;
* the scheduler's wake-ups → its actions are translated as the daemon translates them
  (:mod:`dffd.actuation`, the driver's camera profile) and submitted to the session;
* a frame is *delivered* ``exposure/2 + latency`` after its exposure mid-time → the simulator
  renders it at its exposure time (``render(t)``), the scheduler tags it, the core processes
  it with :meth:`dffd.step.CoreStep.step` (the daemon's estimator thread calls the same step),
  and the core's feedback (σ, burst plan, centroid) goes back to the scheduler.

Nothing waits in real time, so minutes of scenario take seconds. The estimator sees only frames,
tags and the lens table; the bench alone reads the simulator's ground truth to score.

Two other policies run on the same scenario and seed for the baselines that need their own frames:
``sweep`` (classic depth from focus: full focus sweeps, one clean frame per setting) and the
ArUco pass (the dffd policy with the target swapped for an ArUco marker).

The actions' executor is :mod:`hil.lockstep_executor`, the focus sweeps' own policies
:mod:`hil.lockstep_sweep`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np

from dffd.actuation import report_done, report_failed
from dffd.config import DffdConfig
from dffd.core.lens import Lens
from dffd.core.pipeline import PipelineOutput
from dffd.core.pipeline_config import PipelineConfig
from dffd.core.tracking3d_types import TRACKER_KINDS
from dffd.core.types import FrameTag
from dffd.daemon.searchwatch import SearchWatch
from dffd.scheduler import (
    Action,
    FocusInquiry,
    FocusMove,
    Scheduler,
    SchedulerConfig,
    depth_rate_limit,
)
from dffd.step import CoreStep, StepResult
from dffd.wiring import arm_search
from dffd.wiring import pipeline_config as service_pipeline_config
from dffd.wiring import scheduler_config as service_scheduler_config
from drivers.frames import Frame
from drivers.sim.source import FrameTruth
from drivers.sim.virtual_bus import VirtualBus
from drivers.visca.camera import profile_for
from hil.baselines import (
    ArucoBaseline,
    find_blob,
    known_size_depth,
    square_side_for_size,
)
from hil.lockstep_executor import ActionExecutor, ActionOutcome
from hil.lockstep_sweep import CoarseFineState, SweepState
from hil.results import BurstRecord, RunResult
from hil.scenario import Scenario, TrajectorySpec
from hil.simbuild import T_FIRST_FRAME_S, SimSession, build_session
from hil.track3d import Track3DScore, truth_3d

Policy = Literal["dffd", "sweep", "coarse_fine", "aruco"]
# The focus-sweep baselines: the classic full sweep and Krotkov's coarse-to-fine search.
SWEEPS = ("sweep", "coarse_fine")
Progress = Callable[[float], None]  # fraction of the session's scenario time done

# Ground truth per frame kept for scoring measurements of past bursts.
TRUTH_HISTORY_FRAMES = 256


def run_session(
    scenario: Scenario,
    case: str,
    trajectory: TrajectorySpec,
    seed: int,
    *,
    policy: Policy = "dffd",
    duration_s: float | None = None,
    progress: Progress | None = None,
    recorder: FrameSink | None = None,
    on_step: Callable[[StepResult], object] | None = None,
    lens_path: Path | None = None,
) -> RunResult:
    """Run one case of ``scenario`` with ``seed`` in virtual time and return what was measured.

    ``on_step`` sees every core step (output and scheduler feedback) of the dffd policy;
    ``lens_path``: the lens table the estimator is told (default: the scenario's, see
    :func:`hil.simbuild.build_session`).
    """
    duration = scenario.duration_s if duration_s is None else duration_s
    shape = "aruco" if policy == "aruco" else scenario.target.shape
    session = build_session(scenario, trajectory, seed, target_shape=shape, lens_path=lens_path)
    runner = _Runner(scenario, case, seed, session, policy, duration, progress, recorder)
    runner.on_step = on_step
    return runner.run()


class FrameSink(Protocol):
    """Receives every frame with its tag and truth (``--record``); see :mod:`hil.runner`."""

    def add(self, frame: Frame, tag: FrameTag, truth: FrameTruth) -> None:
        """Store one frame with the simulator's truth at its exposure."""


def daemon_config() -> DffdConfig:
    """The daemon's configuration as ``dffd run`` would resolve it with no file (env applies)."""
    return DffdConfig()


def scheduler_config(
    session: SimSession, lens: Lens, config: DffdConfig, overrides: dict[str, Any]
) -> SchedulerConfig:
    """The scheduler configuration, built by the daemon's own builder (+ overrides).

    The simulated camera supplies what the daemon reads off the real one: frame rate, exposure,
    focus speed, frame size and the link's baud rate.
    """
    base = service_scheduler_config(
        config,
        fps=session.fps,
        exposure_s=session.exposure_s,
        focus_speed_counts_per_s=session.device_config.focus_speed_counts_s,
        focal_length_mm=lens.focal_length_mm,
        pixel_pitch_mm=lens.pixel_pitch_mm,
        frame_size=session.frame_size,
        baudrate=session.device_config.baud,
    )
    return dataclasses.replace(base, **overrides) if overrides else base


def pipeline_config(scenario: Scenario, config: DffdConfig) -> PipelineConfig:
    """The estimator configuration as the daemon builds it; the scenario's known size for CF1."""
    base = dataclasses.replace(
        service_pipeline_config(config),
        known_size_m=scenario.target.known_size_m,
        settle_s=scenario.settle_s,
    )
    if not scenario.estimator:
        return base
    overrides = dict(scenario.estimator)
    # Nested sections given as tables (``--set estimator.plan={outer_blur_px=2.0}``) update the
    # defaults field by field.
    for name in ("plan", "fit", "tracker", "kf_noise", "noise_adapt"):
        if isinstance(overrides.get(name), dict):
            overrides[name] = dataclasses.replace(getattr(base, name), **overrides[name])
    return dataclasses.replace(base, **overrides)


class _Runner:
    def __init__(  # noqa: PLR0917 - private, called once from run_session
        self,
        scenario: Scenario,
        case: str,
        seed: int,
        session: SimSession,
        policy: Policy,
        duration: float,
        progress: Progress | None,
        recorder: FrameSink | None,
    ) -> None:
        self.scenario = scenario
        self.session = session
        self.policy = policy
        self.progress = progress
        self.recorder = recorder
        self.on_step: Callable[[StepResult], object] | None = None
        self.lens = Lens.from_toml(session.lens_path)
        self.device = session.rig.device()
        dcfg = daemon_config()
        # The driver's profile of the configured model converts degrees and speed codes.
        self.profile = profile_for(dcfg.camera.model)
        self.link = ActionExecutor(VirtualBus(self.device), self.profile, self._network_changed)
        # Every 3D tracker kind on the same frames: MMAE (published) against IMM and lone CV.
        self.core = CoreStep.build(pipeline_config(scenario, dcfg), self.lens, TRACKER_KINDS)
        self.pipeline = self.core.pipeline
        self.sched_config = scheduler_config(session, self.lens, dcfg, scenario.scheduler)
        self.scheduler = Scheduler(self.sched_config)
        self.search_watch = SearchWatch(self.scheduler)  # logs the sweep as the daemon does
        self.scheduler.set_track_focus(
            self.lens.counts_for_depth(dcfg.scheduler.initial_focus_depth_m)
        )
        mode = "fast" if policy == "dffd" else f"fast-{policy}"
        self.result = RunResult(
            scenario=scenario.name,
            case=case,
            seed=seed,
            mode=mode,
            duration_s=duration,
            settle_s=scenario.settle_s,
            t_start=T_FIRST_FRAME_S,
            best=self.pipeline.config.best,
            track3d=Track3DScore(scenario.settle_s),
        )
        self.daemon_config = dcfg
        self.n_frames = round(duration * session.fps)
        self.truth: dict[int, float] = {}
        self._truth_order: deque[int] = deque()
        self._sweep_owned_move: int | None = None
        self._aruco: ArucoBaseline | None = None
        if policy == "aruco":
            side = session.world.shape.aruco_marker_side_m
            self._aruco = ArucoBaseline(
                marker_side_m=side if side else square_side_for_size(scenario.target.size_m),
                focal_length_px=self.lens.focal_length_mm / self.lens.pixel_pitch_mm,
                frame_size=session.frame_size,
            )
        b = scenario.baselines
        self._sweep: SweepState = (
            CoarseFineState(self.lens, b.coarse_settings, b.fine_settings)
            if policy == "coarse_fine"
            else SweepState(self.lens, b.full_sweep_settings)
        )
        self._sweep_baseline = "coarse_fine" if policy == "coarse_fine" else "full_sweep"
        self._sweep.exposure_s = session.exposure_s
        self.result.notes.extend(session.notes)

    # -- main loop ---------------------------------------------------------------------------
    def run(self) -> RunResult:
        wall0 = time.perf_counter()
        now = 0.0
        self.session.set_time(now)
        self.device.power_up(now)
        if self.policy == "dffd":
            # As the daemon starts: automatic acquisition sweeps pan/tilt if nothing is seen.
            # (The baselines' passes keep the head where they started: the ArUco marker is not
            # the core's target, and the focus sweeps only borrow the centring.)
            arm_search(self.scheduler, self.daemon_config, now)
        k = 0
        while k < self.n_frames:
            t_frame = self.session.delivery_time(k)
            candidates = [t_frame]
            wake = self._wakeup()
            if wake is not None and wake > now:
                candidates.append(wake)
            deadline = self.link.next_deadline()
            if deadline is not None:
                candidates.append(max(deadline, now))
            now = min(candidates)
            self.session.set_time(now)
            for outcome in self.link.poll(now):
                self._dispatch(outcome)
            if now >= t_frame:
                self._frame(k)
                k += 1
                if self.progress is not None and k % 30 == 0:
                    self.progress(k / self.n_frames)
            self._act(now)
        self.result.wall_s = time.perf_counter() - wall0
        self._finish()
        return self.result

    def _wakeup(self) -> float | None:
        if self.policy in SWEEPS:
            times = [self.scheduler.next_wakeup(), self._sweep.wakeup]
            valid = [t for t in times if t is not None]
            return min(valid) if valid else None
        return self.scheduler.next_wakeup()

    def _act(self, now: float) -> None:
        for action in self.scheduler.next_actions(now):
            if self.policy in SWEEPS and isinstance(action, FocusMove | FocusInquiry):
                self._swallow_focus_action(action, now)
                continue
            for outcome in self.link.send(action, now):
                self._dispatch(outcome)
        self.search_watch.update(now)
        if self.policy in SWEEPS:
            move = self._sweep.next_move(now)
            if move is not None:
                for outcome in self.link.send(move, now):
                    self._dispatch(outcome)

    def _swallow_focus_action(self, action: Action, now: float) -> None:
        # In the sweep pass the scheduler only steers pan/tilt: its single initial focus move is
        # reported done at once so it sits in "track" without a plan (no bursts, no inquiries).
        if isinstance(action, FocusMove):
            self.scheduler.on_focus_completed(action.move_id, now)

    def _network_changed(self, now: float) -> None:
        # As the daemon after a re-initialisation: the focus and the head may have moved.
        self.scheduler.invalidate_focus(now)
        self.scheduler.on_pan_tilt_failed(now)

    def _dispatch(self, outcome: ActionOutcome) -> None:
        action = outcome.action
        if self.policy in SWEEPS and isinstance(action, FocusMove):
            # The sweep's own focus moves (the scheduler's were swallowed, see _act).
            if outcome.ok:
                self._sweep.on_done(action.move_id, outcome.t)
            else:
                self._sweep.on_failed(action.move_id, outcome.t)
        elif outcome.ok:
            report_done(self.scheduler, action, outcome.t, outcome.answer, self.profile)
        else:
            report_failed(self.scheduler, action, outcome.t)

    # -- frames --------------------------------------------------------------------------------
    def _frame(self, index: int) -> None:
        t_mid = self.session.frame_time(index)
        tag = self.scheduler.on_frame(index, t_mid)
        frame, truth = self.session.render(index)
        truth_z = truth.z_m
        self._remember_truth(index, truth_z)
        res = self.result
        res.frames += 1
        if self.policy in SWEEPS:
            tag = self._sweep.tag(t_mid, tag)
            res.frames_by_role[tag.role] = res.frames_by_role.get(tag.role, 0) + 1
            self._sweep_frame(frame, tag, truth_z)
            return
        res.frames_by_role[tag.role] = res.frames_by_role.get(tag.role, 0) + 1
        self._pan_tilt_sample(tag, truth)
        if self.recorder is not None:
            self.recorder.add(frame, tag, truth)
        c0 = time.thread_time()
        step = self.core.step(frame, tag)
        res.core_cpu_s.append(time.thread_time() - c0)
        self._score(step.output, frame, tag, truth, published=step.published)
        if step.tracks and step.published and res.track3d is not None:
            res.track3d.add(frame.t - res.t_start, truth_3d(truth), step.tracks)
        step.feedback.apply(self.scheduler)
        if self.on_step is not None:
            self.on_step(step)

    def _score(
        self,
        out: PipelineOutput,
        frame: Frame,
        tag: FrameTag,
        truth: FrameTruth,
        *,
        published: bool = True,
    ) -> None:
        """Score one frame's output: the burst always (its ``…/measurement`` goes out as it is),
        the estimate's depths only when the first-depth gate publishes them (dffd.first_depth:
        the bench scores what a user receives, from the first published estimate on)."""
        truth_z = truth.z_m
        res = self.result
        size = self.scenario.target.size_m
        m = out.measurement
        if m is not None:
            truths = [self.truth[i] for i in m.frame_indices if i in self.truth]
            tz = float(np.mean(truths)) if truths else math.nan
            coeffs = _parabola(m.v_mm, m.costs)
            res.bursts.append(
                BurstRecord(
                    t=m.t,
                    v0_mm=m.v_mm,
                    cost=m.costs,
                    accepted=m.accepted,
                    reason=m.reason,
                    v_hat_mm=m.v_hat_mm if math.isfinite(m.v_hat_mm) else None,
                    coeffs=coeffs,
                    z_m=m.z_m,
                    truth_z_m=tz,
                    truth_v_mm=self.lens.v_from_depth(tz) if math.isfinite(tz) else None,
                )
            )
            res.extra.setdefault("burst_counts", []).append(list(m.focus_counts))
            if m.accepted and m.z_m is not None:
                # Raw z_m scored against the truth at the burst's own exposures.
                # with the σ the core gave it (adapted), when it applied it on this frame
                est0 = out.estimate
                sig = est0.sigma_by.get("measured") if est0 and est0.measured_t == m.t else None
                res.series("measured").add(m.t, m.z_m, tz, sig)
        est = out.estimate
        if est is None:
            return
        res.estimate_frames += 1
        res.r_px.add(frame.t, est.r_px, truth.r_px)
        res.truth_depth.add(frame.t, truth_z, truth_z)
        if not published:
            res.withheld += 1
        for name, z in est.depth_m.items() if published else ():
            if name == "measured" or z is None:
                continue
            res.series(name).add(frame.t, z, truth_z, est.sigma_by.get(name))
        if published and est.beta_m_s is not None:
            res.beta.add(frame.t, est.beta_m_s)
        if published and est.size_m is not None:
            res.size.add(frame.t, est.size_m, size)
        if self.scenario.baselines.known_size and est.r_px > 0:
            z_ks = known_size_depth(
                est.r_px, size, self.lens.focal_length_mm, self.lens.pixel_pitch_mm
            )
            res.baseline("known_size").add(frame.t, z_ks, truth_z)
        if self._aruco is not None:
            z_ar = self._aruco.depth(frame.image)
            if z_ar is not None:
                res.baseline("aruco").add(frame.t, z_ar, truth_z)

    def _pan_tilt_sample(self, tag: FrameTag, truth: FrameTruth) -> None:
        # Pan/tilt diagnostics (truth, for the report only): the target's image motion during
        # the exposure (smear), its centring error, and the head's direction for its reversals.
        w, h = self.session.frame_size
        off = math.hypot(truth.centroid_px[0] - (w - 1) / 2.0, truth.centroid_px[1] - (h - 1) / 2.0)
        self.result.extra.setdefault("pan_tilt_samples", []).append(
            (truth.t - self.result.t_start, tag.role, math.hypot(*truth.motion_px), off,
             truth.pan_deg, truth.tilt_deg)
        )  # fmt: skip

    def _remember_truth(self, index: int, z: float) -> None:
        self.truth[index] = z
        self._truth_order.append(index)
        while len(self._truth_order) > TRUTH_HISTORY_FRAMES:
            self.truth.pop(self._truth_order.popleft(), None)

    # -- sweep policy --------------------------------------------------------------------------
    def _sweep_frame(self, frame: Frame, tag: FrameTag, truth_z: float) -> None:
        blob = find_blob(frame.image)
        centroid = None if blob is None else (blob[0], blob[1])
        self.scheduler.on_estimate(
            frame.t,
            sigma_m=None,
            plan=None,
            centroid_px=centroid,
            pan_deg=tag.pan_deg,
            tilt_deg=tag.tilt_deg,
        )
        done = self._sweep.on_frame(frame, tag, blob, truth_z)
        if done is not None:
            t_peak, z, tz = done
            if z is not None:
                self.result.baseline(self._sweep_baseline).add(t_peak, z, tz)

    def _finish(self) -> None:
        res = self.result
        if self.policy in SWEEPS:
            res.full_sweep_depth_hz = self._sweep.completed / res.duration_s
            res.extra["sweep_settings"] = self._sweep.frames_per_depth
            return
        counts = [sorted(c) for c in res.extra.get("burst_counts", []) if len(c) >= 3]
        if counts:
            spacing = int(np.median([0.5 * (c[-1] - c[0]) for c in counts]))
            # the two sides apart: brackets symmetric in v are not in counts (budget.py)
            sides = (
                int(np.median([c[1] - c[0] for c in counts])),
                int(np.median([c[-1] - c[1] for c in counts])),
            )
            limit = depth_rate_limit(self.sched_config, sides)
            res.depth_limit_hz = limit.depth_hz
            res.extra["median_burst_half_span_counts"] = spacing
            res.extra["median_burst_sides_counts"] = list(sides)
        # bursts the core dropped before a fit (fewer than three frames with a cost), by reason
        res.extra["burst_drops"] = dict(self.pipeline.burst_rejections)
        res.extra["measure_fallbacks"] = self.pipeline.measure_fallbacks
        res.extra["scheduler"] = {
            "bursts_started": self.scheduler.stats.bursts_started,
            "bursts_completed": self.scheduler.stats.bursts_completed,
            "bursts_incomplete": self.scheduler.stats.bursts_incomplete,
            "focus_moves": self.scheduler.stats.focus_moves,
            "pan_tilt_commands": self.scheduler.stats.pan_tilt_commands,
        }
        stats = self.link.bus.stats()
        res.extra["link"] = {
            "commands": self.link.commands_sent,
            "errors": sum(stats.errors_by_code.values()),
            "timeouts": sum(stats.timeouts.values()),
        }
        if self._aruco is not None:
            res.extra["aruco"] = {
                "detections": self._aruco.detections,
                "misses": self._aruco.misses,
            }


def _parabola(v: tuple[float, ...], g: tuple[float, ...]) -> tuple[float, float, float] | None:
    """Least-squares ``g = a v² + b v + c`` through a burst's samples, for the plots only."""
    if len(v) < 3 or len(set(v)) < 3:
        return None
    x = np.asarray(v, dtype=np.float64)
    mid = float(x.mean())
    a2, a1, a0 = np.polyfit(x - mid, np.asarray(g, dtype=np.float64), 2)
    # expand back to raw v: a (v−m)² + b (v−m) + c
    return float(a2), float(a1 - 2 * a2 * mid), float(a0 - a1 * mid + a2 * mid * mid)
