"""The estimation pipeline: tagged frames in, estimates and burst measurements out.

Per frame (pure, synchronous, deterministic; no clock but the frames' own ``t``):

* ``acquiring``/``lost``: look for the target (pending ROI, else near the last position, else the
  whole frame when ``auto_acquire``); on success the contour is refined on that frame.
* every frame: the active contour is updated (transit frames: translation only).
* burst frames: the focus cost (``focus_measure``: (2) or the edge second moment) is taken along
  the normals; when the burst is complete (its
  ``burst_size`` slots, or a track frame / another burst id arrives) the parabola is fitted and a
  :class:`Measurement` is emitted (a burst left with fewer than three frames is not emitted: it is
  counted in :attr:`Pipeline.burst_rejections` with the reason). A burst one of whose frames has
  no edge-moment cost (its blur overflows the normal lines: the first, full-range brackets) is
  fitted with (2) on all its frames and counted in :attr:`Pipeline.measure_fallbacks`.
* rolling bursts (the scheduler's ``rolling`` mode, a triangle lo, mid, hi, mid, lo, … of focus
  settings): the end frames are tagged ``burst`` with slot 2 alone; such a frame closes a burst
  made of the previous end frame (the other side of the bracket), the last tracking frame between
  the two (at the middle: tracking frames carry their focus cost too) and itself. The first end of
  a sequence (or one whose previous end is missing, stale or on the same side) opens a sequence.
* track frames: the normalised size ``s = r p / F`` (``F`` the image distance, i.e. ``v0`` of the
  frame's focus setting under the thin-lens magnification) gives ``ρ`` and the exact transition
  ``s_k/s_{k+1}``; every estimator predicts; a pending accepted measurement is applied; an
  :class:`Estimate` is emitted.

Measurements are *transported* to the current frame with the size invariant ``z s = R``: a burst
at mid-time ``t_b`` yields a size measurement ``R_m = z_m s(t_b)`` and the depth measurement fed to
every estimator at later frames is ``R_m / s`` (exact under the model; removes the staleness of a
held ``z_m``). See docs/estimation.md.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import KW_ONLY, dataclass, field, replace
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.contour import BoundaryObservation, ContourTracker, TrackerConfig, find_target
from dffd.core.filters import (
    CF1,
    CF2,
    DepthKF,
    Differentiator,
    KFNoise,
    KFTraceEvent,
    LPVGains,
    LPVObserver,
)
from dffd.core.filters import cf2_gains as _cf2_gains
from dffd.core.focus import FitConfig, PlanConfig, fit_burst, frame_cost
from dffd.core.focus import plan_burst as _plan_burst
from dffd.core.geometry import VelocityEstimator, camera_point, to_world
from dffd.core.lens import Lens
from dffd.core.noise import NoiseAdaptConfig, model_sigma_v_mm
from dffd.core.uncertainty import Uncertainty
from dffd.literals import FocusMeasure
from drivers.frames import Frame

from .types import FrameTag

logger = logging.getLogger(__name__)

TrackState = Literal["idle", "acquiring", "tracking", "lost"]
EstimatorName = Literal["measured", "cf1", "cf2", "lpv", "kf"]
ESTIMATORS: tuple[EstimatorName, ...] = ("measured", "cf1", "cf2", "lpv", "kf")
Vec3 = tuple[float, float, float]
# Memoised focus settings (lens table look-ups): the counts of a session span a few thousand
# values at most; the cache is emptied when it reaches this size.
V_CACHE_ENTRIES = 4096


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Estimation parameters (defaults documented in docs/estimation.md)."""

    n_normals: int = 64  # Nl of (2)
    search_px: int = 12  # half-length of the normal lines
    settle_s: float = 5.0  # settling time: steady-state statistics start after it
    burst_size: int = 3  # frames of a complete burst
    # Rolling bursts: the previous end must be at most this old (s) to close a burst with.
    rolling_max_span_s: float = 2.0
    # image scale: "pinhole" f/p (docs/design.md §3.4, the reference simulator) or "thin_lens" v0/p
    # (chief ray; lenses whose image size "breathes" with focus)
    magnification: Literal["thin_lens", "pinhole"] = "pinhole"
    transport_measurements: bool = True
    # Burst motion compensation: the target's sharp setting moves during a burst (~0.6 s; at
    # 0.25 m/s and 8 m that is ~2 µm of v against ~0.6 µm of fit noise). The size ratio gives
    # each frame's depth relative to the burst mid-time, z_i = z s(t_mid)/s(t_i), so every focus
    # setting is shifted by v(z_i) − v(z) before the fit (docs/estimation.md).
    compensate_burst_motion: bool = True
    plan_lead_s: float = 0.3  # plan → burst mid-time (slots at ~0, 0.2, 0.6 s at 30 fps)
    # CF1 / CF2 (Lemma 1 from the noise densities)
    cf1_k: float = 1.0  # rad/s
    cf2_nominal_size_m: float | None = None  # None: mean of the first size measurements
    cf2_size_bursts: int = 10  # ... over this many accepted bursts, then frozen (paper: fixed R)
    # Start-up hand-over: the fixed-gain filters (CF1, CF2, LPV) are seeded from the KF (the LPV
    # with both of its states, which mean the same as the KF's) at each of the first accepted
    # bursts, while the KF's covariance converges; a fixed-gain observer with the narrow steady
    # bandwidth would need several 1/λ ≈ 8 s to forget a start-up error. Rolling bursts come at
    # ~2.2 Hz, so 20 bursts ≈ 9 s (swept 8/12/20/30/60 on the five scenarios with hil run
    # --fast after the σ_v re-measurement: LPV ss std static 55/7.1/5.0/4.9/5.1 mm;
    # docs/estimation.md §7).
    warmup_bursts: int = 20
    # Effective time of a depth measurement relative to the mean exposure mid-time of its frames
    # (z_m equals z(t_b + τ)): this fixed part (0: the exposure timing) plus τ̂ estimated online
    # from the innovations (noise_adapt; docs/estimation.md §9). It was a constant 0.03 s fitted
    # to the reference simulator's lean (−13 ms on a held-out lens).
    measurement_time_offset_s: float = 0.0
    # Measurement noise and time offset adapted from the innovations; honest σ per estimator
    noise_adapt: NoiseAdaptConfig = field(default_factory=NoiseAdaptConfig)
    # LPV observer: error poles and the declared ρ range of the gain schedule
    # rad/s: the transported z_m steps once a burst (~1 s) with ~0.5 % noise while ρ is nearly
    # noise-free, so the observer should average ~10 bursts (decay 0.12/s; measured on the
    # reference simulator: ω 0.6 → 0.15 takes LPV from 0.88x to 0.45x of raw z_m's std)
    lpv_omega: float = 0.15
    lpv_zeta: float = 0.8
    kf_noise: KFNoise = field(default_factory=KFNoise)
    differentiator_omega: float = 12.0  # rad/s, bandwidth of ṙ and of the velocity
    # ψ_m for CF1/CF2: "step" = exact size difference over each step (its noise telescopes when
    # the filter integrates it, and it has no lag); "differentiator" = the filtered ṙ (lags 2ζ/ω)
    psi_source: Literal["step", "differentiator"] = "step"
    max_gap_s: float = 2.0  # estimators restart after a gap without tracking longer than this
    auto_acquire: bool = True
    reacquire_every_frames: int = 5  # whole-frame search period while lost (it costs ~ms)
    motion: Literal["similarity", "affine"] = "similarity"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)
    # Set from the service config ([estimators], [target]) by dffd.wiring.pipeline_config, which
    # is where their defaults live: no second default here that a runner could drift onto.
    _: KW_ONLY
    best: EstimatorName
    known_size_m: float | None  # enables CF1
    cf2_sigma_psi: float  # m/s/√Hz (CF2, Lemma 1 from the noise densities)
    cf2_sigma_beta: float  # m/s²/√Hz
    cf2_sigma_z: float  # m·√s
    rho_min: float  # 1/s: ρ = ṙ/r = −ż/z; ±2/s covers 4 m/s at 2 m
    rho_max: float
    # Focus measure of a burst frame (dffd.core.focus.frame_cost): "peak_gradient" is the
    # paper's cost (2); "edge_variance" holds for any PSF but is noisier (docs/estimation.md §8).
    focus_measure: FocusMeasure


@dataclass(frozen=True, slots=True)
class Measurement:
    """One burst: settings, costs, parabola fit and the depth measurement (``…/measurement``)."""

    burst_id: int
    t: float  # mid-time of the burst frames
    frame_indices: tuple[int, ...]
    focus_counts: tuple[int, ...]
    v_mm: tuple[float, ...]
    costs: tuple[float, ...]
    cost_sigmas: tuple[float, ...]
    alpha: float
    v_hat_mm: float
    residual: float
    accepted: bool
    reason: str
    z_m: float | None
    sigma_m: float | None


@dataclass(frozen=True, slots=True)
class Estimate:
    """Everything known at one tracking frame (``…/estimate``)."""

    frame_index: int
    t: float
    state: TrackState
    depth_m: dict[str, float | None]  # measured, cf1, cf2, lpv, kf
    measured_t: float | None  # burst mid-time of ``depth_m["measured"]``
    best: EstimatorName
    z_m: float | None  # the best estimator's depth
    sigma_m: float | None
    beta_m_s: float | None  # CF2 bias estimate β̂
    lpv_b_m_s: float | None  # LPV disturbance estimate
    size_m: float | None  # R̂ = ẑ s
    r_px: float
    rho: float | None  # ṙ/r over the last step, 1/s
    centroid_px: tuple[float, float]
    position_m: Vec3 | None  # camera frame
    velocity_m_s: Vec3 | None
    position_world_m: Vec3 | None
    velocity_world_m_s: Vec3 | None
    pan_deg: float
    tilt_deg: float
    focus_counts: int | None
    inlier_fraction: float
    # σ per estimator (measured, cf1, cf2, lpv, kf; None where it has no value); sigma_m is the
    # best's. Honest σ: adapted noise, correlated measurements, Student-t start-up factor.
    sigma_by: dict[str, float | None] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class PipelineOutput:
    """Result of one :meth:`Pipeline.process` call."""

    state: TrackState
    estimate: Estimate | None
    measurement: Measurement | None
    observation: BoundaryObservation | None


@dataclass(slots=True)
class _BurstSample:
    index: int
    t: float
    counts: int
    v_mm: float
    g: float  # cost of the configured measure (NaN: none on this frame)
    sigma_g: float
    peak: tuple[float, float] | None  # cost (2) when the measure is another one (its fallback)


class Pipeline:
    """Tagged frames → estimates; the scheduler asks it for predictions and burst plans."""

    _cf1: CF1
    _cf2: CF2
    _lpv: LPVObserver
    _kf: DepthKF
    _diff: Differentiator
    _vel_cam: VelocityEstimator
    _vel_world: VelocityEstimator
    _size_meas: float | None  # R_m of the last accepted burst
    _cf2_size: float | None
    _n_accepted: int
    _pending: Measurement | None
    _prev: tuple[float, float] | None  # (t, s) of the last tracking frame
    _initialised: bool
    _last_measured: float | None
    _prev_pos_t: float | None
    _burst: list[_BurstSample]
    _burst_id: int | None
    _burst_frames: int
    _last_end: _BurstSample | None  # the last rolling end frame (the next burst's slot 0)
    _last_mid: _BurstSample | None  # the last tracking frame's cost sample
    _diff_rate: float | None  # filtered ρ̂ = ṡ/s at the last tracking frame

    def __init__(self, config: PipelineConfig, lens: Lens) -> None:
        self.config = config
        self.lens = lens
        tcfg = config.tracker
        if tcfg.n_normals != config.n_normals or tcfg.search_px != config.search_px:
            tcfg = replace(tcfg, n_normals=config.n_normals, search_px=config.search_px)
        self._tracker = ContourTracker(tcfg)
        k1, k2 = _cf2_gains(config.cf2_sigma_psi, config.cf2_sigma_beta, config.cf2_sigma_z)
        self.cf2_gains = (k1, k2)
        self.lpv_gains = LPVGains.from_poles(
            config.lpv_omega, config.lpv_zeta, config.rho_min, config.rho_max
        )
        self._hold = not config.auto_acquire
        self._state: TrackState = "idle" if self._hold else "acquiring"
        self._pending_roi: tuple[int, int, int, int] | None = None
        self._known_size = config.known_size_m
        self._last_box: tuple[float, float, float] | None = None  # cx, cy, r of the last contour
        self._frames_since_search = 0
        self._v_cache: dict[int, float] = {}  # focus counts -> v (mm), see _v_from_counts
        # Bursts not emitted (fewer than three frames), by reason.
        self.burst_rejections: Counter[str] = Counter()
        # Bursts fitted with cost (2) because a frame had no cost of the configured measure.
        self.measure_fallbacks = 0
        self.kf_trace: list[KFTraceEvent] | None = None  # see record_kf
        self._reset_estimators()

    # -- public API -------------------------------------------------------------------------
    @property
    def state(self) -> TrackState:
        """idle (released: no search) / acquiring / tracking / lost."""
        return self._state

    def acquire_roi(self, x: int, y: int, w: int, h: int) -> None:
        """Acquire the target inside this ROI on the next frame (drops the current target)."""
        if w <= 0 or h <= 0:
            raise ValueError(f"ROI needs a positive size, got {w}x{h}")
        self._pending_roi = (int(x), int(y), int(w), int(h))
        self._hold = False
        self._tracker.reset()
        self._state = "acquiring"
        self._reset_estimators()

    def acquire_auto(self) -> None:
        """Search the whole frame for the target from the next frame (drops the current target)."""
        self._pending_roi = None
        self._hold = False
        self._tracker.reset()
        self._state = "acquiring"
        self._last_box = None
        self._reset_estimators()

    def release(self) -> None:
        """Stop tracking: ``idle``, no search, until :meth:`acquire_roi` or :meth:`acquire_auto`."""
        self._tracker.reset()
        self._pending_roi = None
        self._hold = True
        self._state = "idle"
        self._last_box = None
        self._reset_estimators()

    def record_kf(self, trace: list[KFTraceEvent]) -> None:
        """Append every Kalman-filter step to ``trace`` from now on (an offline smoother's input,
        dffd.core.smoother); the daemon does not record."""
        self.kf_trace = trace
        self._kf.trace = trace

    def set_known_size(self, meters: float | None) -> None:
        """Set (enables CF1) or clear the target's known size."""
        if meters is not None and not meters > 0:
            raise ValueError(f"known size must be > 0 m, got {meters}")
        self._known_size = meters
        self._cf1 = CF1(self.config.cf1_k)

    def predicted_depth(self) -> tuple[float, float] | None:
        """(ẑ of the best estimator, σ) at the last tracking frame, or None before the first fix.

        σ is the Kalman filter's (the only estimator with a covariance), a fair proxy for all.
        """
        z = self._depth(self.config.best)
        if z is None or self._kf.sigma is None:
            return None
        return z, self._kf.sigma

    def plan_burst(self, current_counts: int) -> tuple[int, int, int]:
        """Three focus counts for the next burst, ordered to minimise motor travel.

        The bracket is centred on the depth predicted ``plan_lead_s`` ahead (the burst's mid-time
        comes that much after the plan): the parabola is only a model of the cost, and a bracket
        off-centre by the target's motion biased the vertex along the motion (measured: z_m
        error ≈ 0.07 s × ż on the reference simulator with a centred-on-now bracket).
        """
        pred = self.predicted_depth()
        z, s = (None, None) if pred is None else pred
        if z is not None and self._prev is not None and self._diff_rate is not None:
            z = z * math.exp(-self._diff_rate * self.config.plan_lead_s)
        return _plan_burst(self.lens, current_counts, z, s, self.config.plan)

    def tracking_counts(self) -> int | None:
        """Focus counts that focus the predicted depth (for tracking frames), or None."""
        pred = self.predicted_depth()
        return None if pred is None else self.lens.counts_for_depth(pred[0])

    def process(self, frame: Frame, tag: FrameTag) -> PipelineOutput:
        """Consume one frame and its tag."""
        measurement: Measurement | None = None
        if self._burst_id is not None and tag.burst is not None and tag.burst[0] != self._burst_id:
            measurement = self._finish_burst(None)  # a new burst before any tracking frame
        if not self._tracker.active and not self._try_acquire(frame):
            if tag.role == "track":
                measurement = self._finish_burst(None) or measurement
            return PipelineOutput(self._state, None, measurement, None)
        # Every frame follows scale too (transit frames included): r is read on track frames
        # only, but a contour frozen in size through a long focus travel (the first bursts span
        # the working range: 40 transit frames) drifts out of the outlier gate and the target
        # is lost mid-burst (measured on the reference simulator).
        obs = self._tracker.update(frame.image, frame.t, self.config.motion)
        if self._tracker.lost:
            logger.info("target lost at frame %d (t=%.3f)", frame.index, frame.t)
            c = obs.centroid
            self._last_box = (c[0], c[1], obs.r_px)
            self._tracker.reset()
            self._state = "lost"
            self._discard_burst()
            self._last_end = self._last_mid = None
            return PipelineOutput(self._state, None, measurement, obs)
        if not obs.ok:
            if tag.role == "track":
                measurement = self._finish_burst(None) or measurement
            return PipelineOutput(self._state, None, measurement, obs)
        c = obs.centroid
        self._last_box = (c[0], c[1], obs.r_px)
        if tag.role == "burst" and tag.focus_counts is not None:
            self._add_burst_sample(frame, tag, obs)
            return PipelineOutput(self._state, None, measurement, obs)
        if tag.role != "track" or tag.focus_counts is None:
            return PipelineOutput(self._state, None, measurement, obs)
        # A tracking frame is at the best focus: the middle of a rolling burst.
        self._last_mid = self._cost_sample(frame, tag.focus_counts, obs)
        estimate, done = self._track_frame(frame, tag, obs)
        return PipelineOutput(self._state, estimate, done or measurement, obs)

    # -- acquisition --------------------------------------------------------------------------
    def _try_acquire(self, frame: Frame) -> bool:
        img = frame.image
        gray: npt.NDArray[np.uint8] = np.ascontiguousarray(
            img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), dtype=np.uint8
        )
        rois: list[tuple[int, int, int, int] | None] = []
        if self._pending_roi is not None:
            rois.append(self._pending_roi)
        elif self._hold:
            return False
        else:
            if self._last_box is not None:
                cx, cy, r = self._last_box
                half = 2.0 * r + 3 * self.config.search_px
                rois.append((int(cx - half), int(cy - half), int(2 * half), int(2 * half)))
            self._frames_since_search += 1
            if self._last_box is None or (
                self._frames_since_search >= self.config.reacquire_every_frames
            ):
                self._frames_since_search = 0
                rois.append(None)
        for roi in rois:
            poly = find_target(gray, roi, self._tracker.config.min_radius_px)
            if poly is not None and self._tracker.start(gray, poly, frame.t):
                logger.info("target acquired at frame %d (roi=%s)", frame.index, roi)
                self._pending_roi = None
                self._state = "tracking"
                return True
        return False

    # -- bursts ---------------------------------------------------------------------------------
    def _add_burst_sample(self, frame: Frame, tag: FrameTag, obs: BoundaryObservation) -> None:
        # The fit waits for the next tracking frame: its size brackets the burst in time, so
        # each burst frame's depth relative to the mid-time is interpolated, not extrapolated.
        assert tag.focus_counts is not None
        bid, slot = tag.burst if tag.burst is not None else (-1, 0)
        sample = self._cost_sample(frame, tag.focus_counts, obs)
        if self._burst_id is None and slot == self.config.burst_size - 1 and slot > 0:
            self._add_rolling_end(bid, sample)
            return
        if self._burst_id is None:
            self._burst_id = bid
        if sample is not None:
            self._burst.append(sample)
        self._burst_frames += 1

    def _add_rolling_end(self, bid: int, sample: _BurstSample | None) -> None:
        """A last slot with none before it: a rolling end; close a burst with the previous end
        and the tracking frame between them (see the module docstring)."""
        prev, mid = self._last_end, self._last_mid
        self._last_end = sample
        if sample is None:
            return
        if (
            prev is None
            or mid is None
            or not prev.t < mid.t < sample.t
            or sample.t - prev.t > self.config.rolling_max_span_s
            or (prev.counts - mid.counts) * (sample.counts - mid.counts) >= 0
        ):
            logger.debug("rolling burst %d opens a sequence (no previous end to close)", bid)
            return
        self._burst = [prev, mid, sample]
        self._burst_id = bid
        self._burst_frames = 3

    def _cost_sample(
        self, frame: Frame, counts: int, obs: BoundaryObservation
    ) -> _BurstSample | None:
        trim = self._tracker.config.trim_fraction
        measure = self.config.focus_measure
        cost = frame_cost(obs, measure, trim)
        peak = None if measure == "peak_gradient" else frame_cost(obs, "peak_gradient", trim)
        if cost is None and peak is None:
            return None
        g, sigma_g = (math.nan, math.nan) if cost is None else cost
        return _BurstSample(
            frame.index, frame.t, counts, self._v_from_counts(counts), g, sigma_g, peak
        )

    def _discard_burst(self) -> None:
        self._burst = []
        self._burst_id = None
        self._burst_frames = 0

    def _finish_burst(self, after: tuple[float, float] | None) -> Measurement | None:
        """Fit the pending burst; ``after`` = (t, s) of the tracking frame that follows it."""
        if self._burst_id is None:
            return None
        samples, bid = self._burst, self._burst_id
        self._discard_burst()
        if len(samples) < 3:
            # Not a burst (a claimed frame was dropped, the contour failed on a slot, the link
            # cut it short): nothing to fit and nothing the ``…/measurement`` schema accepts.
            reason = f"{len(samples)} of 3 frames with a focus cost"
            self.burst_rejections[reason] += 1
            logger.debug("burst %d rejected: %s", bid, reason)
            return None
        t_sum = 0.0
        for s in samples:  # sequential sum (as np.mean of a few values), no array
            t_sum += s.t
        t_mid = t_sum / len(samples)
        if any(math.isnan(s.g) for s in samples):
            # one frame's blur overflowed the edge-moment window: the whole burst on cost (2)
            if any(s.peak is None for s in samples):
                reason = "a frame without a focus cost"
                self.burst_rejections[reason] += 1
                logger.debug("burst %d rejected: %s", bid, reason)
                return None
            samples = [replace(s, g=s.peak[0], sigma_g=s.peak[1]) for s in samples if s.peak]
            self.measure_fallbacks += 1
        v = [s.v_mm for s in samples]
        g = [s.g for s in samples]
        sg = [s.sigma_g for s in samples]
        fit = fit_burst(v, g, sg, self.lens, self.config.fit)
        log_ratio = self._log_size_ratios([s.t for s in samples], t_mid, after)
        if log_ratio is not None:
            z_ref = fit.z_m if fit.accepted else self._depth(self.config.best)
            for _ in range(2):  # the shift depends (weakly) on the depth it is computed at
                if z_ref is None or not z_ref > 0:
                    break
                v_ref = self.lens.v_from_depth(z_ref)
                # z_i = z s(t_mid)/s(t_i): the sharp setting at frame i is v(z_i)
                v_comp = [
                    vi - (self.lens.v_from_depth(z_ref * math.exp(-lr)) - v_ref)
                    for vi, lr in zip(v, log_ratio, strict=True)
                ]
                fit = fit_burst(v_comp, g, sg, self.lens, self.config.fit)
                z_ref = fit.z_m if fit.accepted else None
        m = Measurement(
            burst_id=bid,
            t=t_mid,
            frame_indices=tuple(s.index for s in samples),
            focus_counts=tuple(s.counts for s in samples),
            v_mm=tuple(s.v_mm for s in samples),
            costs=tuple(s.g for s in samples),
            cost_sigmas=tuple(s.sigma_g for s in samples),
            alpha=fit.alpha,
            v_hat_mm=fit.v_hat_mm,
            residual=fit.residual,
            accepted=fit.accepted,
            reason=fit.reason,
            z_m=fit.z_m,
            sigma_m=fit.sigma_m,
        )
        if fit.accepted:
            self._pending = m
        else:
            logger.debug("burst %d rejected: %s", bid, fit.reason)
        return m

    # -- estimators -----------------------------------------------------------------------------
    def _reset_estimators(self) -> None:
        self._reset_filters_keep_tracking()
        self._burst = []
        self._burst_id = None
        self._burst_frames = 0
        self._last_end = None
        self._last_mid = None

    def _image_distance_mm(self, counts: int) -> float:
        if self.config.magnification == "pinhole":
            return self.lens.focal_length_mm
        return self._v_from_counts(counts)

    def _v_from_counts(self, counts: int) -> float:
        """``lens.v_from_counts``, memoised: a PCHIP evaluation costs ~20 µs, and the scheduler
        returns to the same few focus settings frame after frame."""
        v = self._v_cache.get(counts)
        if v is None:
            if len(self._v_cache) >= V_CACHE_ENTRIES:
                self._v_cache.clear()
            v = self._v_cache[counts] = self.lens.v_from_counts(counts)
        return v

    def _depth(self, name: EstimatorName) -> float | None:
        if not self._initialised:
            return None
        if name == "cf1":
            return self._cf1.z if self._known_size is not None else None
        if name == "cf2":
            return self._cf2.z
        if name == "lpv":
            return self._lpv.z
        if name == "kf":
            return self._kf.z
        return self._last_measured

    def _track_frame(
        self, frame: Frame, tag: FrameTag, obs: BoundaryObservation
    ) -> tuple[Estimate, Measurement | None]:
        assert tag.focus_counts is not None
        cfg = self.config
        t = frame.t
        f_img = self._image_distance_mm(tag.focus_counts)
        s = obs.r_px * self.lens.pixel_pitch_mm / f_img  # = R / z
        rho: float | None = None
        if self._prev is not None and t - self._prev[0] > cfg.max_gap_s:
            self._reset_filters_keep_tracking()
        dt = 0.0 if self._prev is None else t - self._prev[0]
        ratio = 1.0 if self._prev is None else self._prev[1] / s
        if dt > 0:
            rho = math.log(1.0 / ratio) / dt
        _, sdot = self._diff.update(s, dt)
        self._diff_rate = sdot / s if dt > 0 else None  # ρ̂ = ṡ/s, filtered (plan lead only)
        self._last_measured = None
        measured_t: float | None = None
        done = self._finish_burst((t, s))
        if self._initialised and dt > 0:
            self._step_filters(dt, s, sdot, rho if rho is not None else 0.0, ratio)
        pending, self._pending = self._pending, None
        if pending is not None and pending.z_m is not None and pending.sigma_m is not None:
            # the fit's σ (cost noise) and the parabola model's error at the vertex's offset
            sigma_z = math.hypot(
                pending.sigma_m,
                abs(self.lens.dz_dv(pending.v_hat_mm))
                * model_sigma_v_mm(pending.v_mm, pending.v_hat_mm, cfg.focus_measure),
            )
            s_b = self._size_at(pending.t + cfg.measurement_time_offset_s, t, s)
            # the lean τ̂ of the vertex, estimated online on the size invariant (noise.py)
            rate = self._diff_rate or 0.0
            tau = self._unc.observe_size(
                math.log(pending.z_m * s_b), rate, sigma_z / pending.z_m, pending.frame_indices
            )
            s_b *= math.exp(rate * tau)
            size_m = pending.z_m * s_b
            self._size_meas = size_m
            self._last_measured = pending.z_m
            measured_t = pending.t
            y_now = size_m / s
            sigma_now = sigma_z * y_now / pending.z_m
            self._n_accepted += 1
            if self._n_accepted <= cfg.cf2_size_bursts and cfg.cf2_nominal_size_m is None:
                n = self._n_accepted
                prev_size = self._cf2_size if self._cf2_size is not None else size_m
                self._cf2_size = prev_size + (size_m - prev_size) / n  # running mean
            if not self._initialised:
                self._kf.reset(y_now, max(sigma_now, 1e-3))
                self._unc.start(max(sigma_now, 1e-3), pending.frame_indices)
                self._initialised = True
            else:
                # the noise the KF is told is adapted from its innovations (noise.py)
                innov = y_now - (self._kf.z or y_now)
                kf_sigma = self._unc.measurement(
                    innov, sigma_now, self._kf.p, pending.frame_indices
                )
                self._kf.update(y_now, kf_sigma)
            if self._n_accepted <= cfg.warmup_bursts:
                self._hand_over(y_now)
        self._prev = (t, s)
        estimate = self._make_estimate(
            frame, tag, obs, s=s, rho=rho, measured_t=measured_t, f_img=f_img
        )
        return estimate, done

    def _log_size_ratios(
        self, times: list[float], t_mid: float, after: tuple[float, float] | None
    ) -> list[float] | None:
        """ln(s(t_i)/s(t_mid)) for burst frames, ln-interpolated between the tracking frames
        around the burst; None when those are not both known (no compensation then)."""
        if not self.config.compensate_burst_motion or after is None or self._prev is None:
            return None
        (t0, s0), (t1, s1) = self._prev, after
        if not t0 < t1 or t1 - t0 > self.config.max_gap_s:
            return None
        rate = math.log(s1 / s0) / (t1 - t0)
        return [rate * (ti - t_mid) for ti in times]

    def _size_at(self, t_b: float, t_now: float, s_now: float) -> float:
        """Normalised size at the burst mid-time, ln-interpolated between tracking frames."""
        if not self.config.transport_measurements or self._prev is None:
            return s_now
        t0, s0 = self._prev
        if t_now <= t0:
            return s_now
        # A rolling burst's mid-time can precede the last tracking frame (its middle frame) a
        # little: ln-extrapolate back by at most one step.
        w = min(max((t_b - t0) / (t_now - t0), -1.0), 1.0)
        return math.exp((1 - w) * math.log(s0) + w * math.log(s_now))

    def _reset_filters_keep_tracking(self) -> None:
        cfg = self.config
        self._cf1 = CF1(cfg.cf1_k)
        self._cf2 = CF2(*self.cf2_gains)
        self._lpv = LPVObserver(self.lpv_gains)
        self._kf = DepthKF(cfg.kf_noise, self.kf_trace)
        self._diff = Differentiator(cfg.differentiator_omega)
        self._unc = Uncertainty(
            cfg.kf_noise,
            cfg.noise_adapt,
            cf1_k=cfg.cf1_k,
            cf2_gains=self.cf2_gains,
            lpv=self.lpv_gains,
        )
        self._vel_cam = VelocityEstimator(cfg.differentiator_omega / 3)
        self._vel_world = VelocityEstimator(cfg.differentiator_omega / 3)
        self._size_meas = None  # R_m of the last accepted burst
        self._cf2_size = cfg.cf2_nominal_size_m
        self._n_accepted = 0
        self._pending = None
        self._prev = None  # (t, s) of the last tracking frame
        self._initialised = False
        self._last_measured = None
        self._prev_pos_t = None
        self._diff_rate = None

    def _hand_over(self, y_now: float) -> None:
        """Seed the fixed-gain filters from the KF's estimate (start-up, see ``warmup_bursts``)."""
        z0 = self._kf.z if self._kf.z is not None else y_now
        b0 = self._kf.b if self._kf.b is not None else 0.0
        self._cf1.reset(z0)
        self._cf2.reset(z0)
        self._lpv.reset(z0, b0)
        self._unc.hand_over()

    def _step_filters(self, dt: float, s: float, sdot: float, rho: float, ratio: float) -> None:
        assert self._size_meas is not None
        assert self._prev is not None
        # the last size measurement seen at the image size: y(τ) = R_m / s(τ) = y0 e^{−ρτ}
        y0 = self._size_meas / self._prev[1]
        lam = -rho
        if self.config.psi_source == "step":
            inv_rate = (1.0 / s - 1.0 / self._prev[1]) / dt  # d(1/s)/dt over the step, exact
        else:
            inv_rate = -sdot / (s * s)
        if self._known_size is not None:
            self._cf1.step(dt, y0, inv_rate * self._known_size, lam)
        cf2_size = self._cf2_size if self._cf2_size is not None else self._size_meas
        self._cf2.step(dt, y0, inv_rate * cf2_size, lam)
        self._lpv.step(dt, rho, y0, lam)
        self._kf.predict(ratio, dt)
        self._unc.predict(dt, ratio, rho, self._kf.z or y0)

    def _make_estimate(
        self,
        frame: Frame,
        tag: FrameTag,
        obs: BoundaryObservation,
        *,
        s: float,
        rho: float | None,
        measured_t: float | None,
        f_img: float,
    ) -> Estimate:
        cfg = self.config
        depth: dict[str, float | None] = {name: self._depth(name) for name in ESTIMATORS}
        sigma_by = self._unc.sigmas(depth)
        z = depth[cfg.best]
        h, w = frame.image.shape[:2]
        dt = 0.0 if self._prev_pos_t is None else frame.t - self._prev_pos_t
        pos = pos_w = vel = vel_w = None
        if z is not None:
            pos = camera_point(obs.centroid, z, (w, h), self.lens.pixel_pitch_mm, f_img)
            pos_w = to_world(pos, tag.pan_deg, tag.tilt_deg)
            vel = self._vel_cam.update(pos, dt)
            vel_w = self._vel_world.update(pos_w, dt)
            self._prev_pos_t = frame.t
        return Estimate(
            frame_index=frame.index,
            t=frame.t,
            state=self._state,
            depth_m=depth,
            measured_t=measured_t,
            best=cfg.best,
            z_m=z,
            sigma_m=sigma_by[cfg.best] if z is not None else None,
            beta_m_s=self._cf2.beta if self._initialised else None,
            lpv_b_m_s=self._lpv.b if self._initialised else None,
            size_m=None if z is None else z * s,
            r_px=obs.r_px,
            rho=rho,
            centroid_px=obs.centroid,
            position_m=pos,
            velocity_m_s=vel,
            position_world_m=pos_w,
            velocity_world_m_s=vel_w,
            pan_deg=tag.pan_deg,
            tilt_deg=tag.tilt_deg,
            focus_counts=tag.focus_counts,
            inlier_fraction=obs.inlier_fraction,
            sigma_by=sigma_by,
        )
