"""The estimation pipeline: tagged frames in, estimates and burst measurements out.

Per frame (pure, synchronous, deterministic; no clock but the frames' own ``t``):

* ``acquiring``/``lost``: look for the target (pending ROI, else near the last position, else the
  whole frame when ``auto_acquire``); on success the contour is refined on that frame.
* every frame: the active contour is updated (:mod:`dffd.core.contour`).
* burst frames (and tracking frames, the middle of a rolling burst): the focus cost is taken
  along the normals and gathered into bursts, fitted when the next tracking frame arrives
  (:mod:`dffd.core.bursts`); an accepted fit is a :class:`Measurement`.
* every frame with a contour, whatever its role: the normalised size ``s = r p / F`` (``F`` the
  image distance: the focal length, or ``v0`` of the frame's focus setting under the thin-lens
  magnification) gives ``ρ`` and the exact transition ``s_k/s_{k+1}``; every estimator predicts
  (:mod:`dffd.core.estimators`); at a tracking frame a pending accepted measurement is applied;
  an :class:`Estimate` is emitted — estimates come at the frame rate.

Measurements are *transported* to the current frame with the size invariant ``z s = R``: a burst
at mid-time ``t_b`` yields a size measurement ``R_m = z_m s(t_b)`` (``s(t_b)`` from the sizes of
the frames around it, :mod:`dffd.core.sizes`) and the depth measurement fed to every estimator
at later frames is ``R_m / s`` (exact under the model; removes the staleness of a held ``z_m``).
See docs/estimation.md.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import replace

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.acquisition import find_target
from dffd.core.bursts import BurstAssembler, FocusSettings
from dffd.core.clipped import ClippedHint
from dffd.core.contour import BoundaryObservation, ContourTracker
from dffd.core.estimators import EstimatorBank
from dffd.core.filters import Differentiator, KFTraceEvent
from dffd.core.focus import plan_burst as _plan_burst
from dffd.core.geometry import VelocityEstimator, camera_point, image_shift, to_world
from dffd.core.lens import Lens
from dffd.core.outputs import (
    ESTIMATORS,
    Estimate,
    EstimatorName,
    Measurement,
    PipelineOutput,
    TrackState,
    Vec3,
)
from dffd.core.pipeline_config import (
    ACQUIRE_DOWNSCALE,
    REACQUIRE_VELOCITY_GAP_S,
    SIZE_EDGE_WIDTHS,
    SIZE_HISTORY_FRAMES,
    SIZE_JUMP_MAX_BLUR_PX,
    SIZE_JUMP_MAX_GAP_S,
    PipelineConfig,
)
from dffd.core.sizes import SizeHistory, SizeOffset
from drivers.frames import Frame

from .types import FrameTag

__all__ = [
    "ESTIMATORS",
    "Estimate",
    "EstimatorName",
    "Measurement",
    "Pipeline",
    "PipelineOutput",
    "TrackState",
    "Vec3",
]

logger = logging.getLogger(__name__)


class Pipeline:
    """Tagged frames → estimates; the scheduler asks it for predictions and burst plans."""

    def __init__(self, config: PipelineConfig, lens: Lens) -> None:
        self.config = config
        self.lens = lens
        tcfg = config.tracker
        if tcfg.n_normals != config.n_normals or tcfg.search_px != config.search_px:
            tcfg = replace(tcfg, n_normals=config.n_normals, search_px=config.search_px)
        if config.focus_measure == "peak_gradient" and tcfg.edge_samples:
            tcfg = replace(tcfg, edge_samples=False)  # no edge moments are asked for
        self._tracker = ContourTracker(tcfg)
        self._settings = FocusSettings(lens)
        self._bursts = BurstAssembler(
            self._settings,
            fit=config.fit,
            focus_measure=config.focus_measure,
            trim_fraction=tcfg.trim_fraction,
            burst_size=config.burst_size,
            rolling_max_span_s=config.rolling_max_span_s,
            vertex_response=config.vertex_response,
        )
        self._bank = EstimatorBank(config, lens)
        self.cf2_gains = self._bank.cf2_gains
        self.lpv_gains = self._bank.lpv_gains
        self._hold = not config.auto_acquire
        self._state: TrackState = "idle" if self._hold else "acquiring"
        self._pending_roi: tuple[int, int, int, int] | None = None
        self._last_box: tuple[float, float, float] | None = None  # cx, cy, r of the last contour
        self._last_box_head = (0.0, 0.0)  # the head's pan/tilt on _last_box's frame
        # the head's pan/tilt at the contour's last frame (its image motion to the next one)
        self._contour_head = (0.0, 0.0)
        # the last frame the target was seen on: its time, centroid (px) and the head's pan/tilt
        self._last_seen: tuple[float, tuple[float, float], tuple[float, float]] | None = None
        self._frames_since_search = 0
        self._candidate: tuple[float, float] | None = None  # a cut-off target (clipped.py)
        self._hint = ClippedHint(lens.focal_length_mm / lens.pixel_pitch_mm)
        self._ever_tracked = False  # a target was acquired since the start
        self._reset_estimators()

    @property
    def burst_rejections(self) -> Counter[str]:
        """Bursts not emitted (fewer than three frames with a cost), by reason."""
        return self._bursts.rejections

    @property
    def measure_fallbacks(self) -> int:
        """Bursts fitted with cost (2) because a frame had no cost of the configured measure."""
        return self._bursts.measure_fallbacks

    @property
    def size_offset_px(self) -> float | None:
        """The estimated size offset δ (px), or None (off, or before two bursts)."""
        est = None if self._offset is None else self._offset.estimate()
        if est is None:
            return None
        return est[0] * self.lens.focal_length_mm / self.lens.pixel_pitch_mm

    @property
    def size_measurement(self) -> tuple[float, float] | None:
        """``(R, σ_R)`` (m) measured by the burst applied at the last frame with an estimate —
        its depth times the image size at its lean-corrected time (docs/estimation.md §9) — or
        None when that frame applied none."""
        bank = self._bank
        if self._last_measured is None or bank.size_meas is None or bank.size_meas_sigma is None:
            return None
        return bank.size_meas, bank.size_meas_sigma

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
        self._last_seen = None  # another target: not the last one's velocity
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
        self._last_seen = None
        self._candidate = None
        self._hint.reset()
        self._reset_estimators()

    def release(self) -> None:
        """Stop tracking: ``idle``, no search, until :meth:`acquire_roi` or :meth:`acquire_auto`."""
        self._tracker.reset()
        self._pending_roi = None
        self._hold = True
        self._state = "idle"
        self._last_box = None
        self._last_seen = None
        self._candidate = None
        self._hint.reset()
        self._reset_estimators()

    def record_kf(self, trace: list[KFTraceEvent]) -> None:
        """Append every Kalman-filter step to ``trace`` from now on (an offline smoother's input,
        dffd.core.smoother); the daemon does not record."""
        self._bank.record_kf(trace)

    def set_known_size(self, meters: float | None) -> None:
        """Set (enables CF1) or clear the target's known size."""
        if meters is not None and not meters > 0:
            raise ValueError(f"known size must be > 0 m, got {meters}")
        self._bank.set_known_size(meters)

    def predicted_depth(self) -> tuple[float, float] | None:
        """(ẑ of the best estimator, σ) at the last tracking frame, or None before the first fix.

        σ is the Kalman filter's (the only estimator with a covariance), a fair proxy for all.
        """
        z = self._depth(self.config.best)
        sigma = self._bank.sigma
        if z is None or sigma is None:
            return None
        return z, sigma

    def plan_burst(self, current_counts: int) -> tuple[int, int, int]:
        """Three focus counts for the next burst, ordered to minimise motor travel.

        The bracket is centred on the depth predicted ``plan_lead_s`` ahead (the burst's mid-time
        comes that much after the plan): the parabola is only a model of the cost, and a bracket
        off-centre by the target's motion biased the vertex along the motion (measured: z_m
        error ≈ 0.07 s × ż on the reference simulator with a centred-on-now bracket).
        """
        return self.plan_burst_for(current_counts, self.predicted_depth())

    def plan_burst_for(
        self, current_counts: int, pred: tuple[float, float] | None
    ) -> tuple[int, int, int]:
        """:meth:`plan_burst` from ``pred``, the :meth:`predicted_depth` the caller holds."""
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
        pending_id = self._bursts.pending_id
        if pending_id is not None and tag.burst is not None and tag.burst[0] != pending_id:
            measurement = self._finish_burst()  # a new burst before any tracking frame
        if not self._tracker.active and not self._try_acquire(frame, tag):
            if tag.role == "track":
                measurement = self._finish_burst() or measurement
            return PipelineOutput(self._state, None, measurement, None, self._candidate)
        # Every frame follows scale too (transit frames included): a contour frozen in size
        # through a long focus travel (the first bursts span the working range: 40 transit
        # frames) drifts out of the outlier gate and the target is lost mid-burst (measured on
        # the reference simulator).
        head = (tag.pan_deg, tag.tilt_deg)
        shift = (0.0, 0.0)
        if self.config.compensate_head_motion:
            shift = self._head_shift(frame, self._tracker.centroid, self._contour_head, head)
        self._contour_head = head
        obs = self._tracker.update(frame.image, frame.t, self.config.motion, shift)
        if self._tracker.lost:
            logger.info("target lost at frame %d (t=%.3f)", frame.index, frame.t)
            c = obs.centroid
            self._last_box = (c[0], c[1], obs.r_px)
            self._last_box_head = head
            self._tracker.reset()
            self._state = "lost"
            self._bursts.reset()
            return PipelineOutput(self._state, None, measurement, obs)
        if not obs.ok:
            if tag.role == "track":
                measurement = self._finish_burst() or measurement
            return PipelineOutput(self._state, None, measurement, obs)
        c = obs.centroid
        self._last_box = (c[0], c[1], obs.r_px)
        self._last_box_head = head
        self._last_seen = (frame.t, c, head)
        if tag.focus_counts is not None:
            if tag.role == "burst":
                self._bursts.add(frame.index, frame.t, tag.focus_counts, tag.burst, obs)
            elif tag.role == "track":
                # A tracking frame is at the best focus: the middle of a rolling burst.
                self._bursts.set_middle(frame.index, frame.t, tag.focus_counts, obs)
        # Every frame with a contour steps the estimators and yields an estimate (burst and
        # transit frames too: their size is as good as a tracking frame's, docs/estimation.md
        # §11); a tracking frame also closes the pending burst.
        estimate, done = self._frame_estimate(frame, tag, obs)
        return PipelineOutput(self._state, estimate, done or measurement, obs)

    # -- acquisition --------------------------------------------------------------------------
    def _try_acquire(self, frame: Frame, tag: FrameTag) -> bool:
        img = frame.image
        gray: npt.NDArray[np.uint8] = img
        if img.ndim != 2 or img.dtype != np.uint8 or not img.flags.c_contiguous:
            gray = np.ascontiguousarray(
                img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), dtype=np.uint8
            )
        # (the frame's own array when it is gray already: the tracker then reuses the gradient
        # it started the contour on for the update of the same frame)
        rois: list[tuple[int, int, int, int] | None] = []
        if self._pending_roi is not None:
            rois.append(self._pending_roi)
        elif self._hold:
            return False
        else:
            if self._last_box is not None:
                cx, cy, r = self._last_box
                if self.config.compensate_head_motion:
                    # where the last contour's direction is now: the head goes on turning after
                    # a loss (its drive, then the search sweep), and a target that stopped
                    # where it was lost is there, not at its old pixel
                    head = (tag.pan_deg, tag.tilt_deg)
                    dx, dy = self._head_shift(frame, (cx, cy), self._last_box_head, head)
                    cx, cy = cx + dx, cy + dy
                half = 2.0 * r + 3 * self.config.search_px
                rois.append((int(cx - half), int(cy - half), int(2 * half), int(2 * half)))
            self._frames_since_search += 1
            if self._last_box is None or (
                self._frames_since_search >= self.config.reacquire_every_frames
            ):
                self._frames_since_search = 0
                rois.append(None)
        for roi in rois:
            # the whole frame is searched on a coarser copy (ACQUIRE_DOWNSCALE), an ROI as is
            scale = 1 if roi is not None else ACQUIRE_DOWNSCALE
            poly = find_target(gray, roi, self._tracker.config.min_radius_px, downscale=scale)
            if poly is not None and self._tracker.start(gray, poly, frame.t):
                logger.info("target acquired at frame %d (roi=%s)", frame.index, roi)
                self._contour_head = (tag.pan_deg, tag.tilt_deg)
                self._seed_velocity(frame, tag)
                self._candidate = None
                self._ever_tracked = True
                self._pending_roi = None
                self._state = "tracking"
                return True
        if rois and rois[-1] is None and not self._ever_tracked:
            # Nothing whole in the frame before any sighting: a target cut by its edge is where
            # to turn (else a target that starts half out of view and moves away is never seen
            # again). After a sighting and a loss the scheduler's search sweep owns the hunt.
            # The hint checks itself: a blob turned to must come into view whole and be taken
            # here, else it is rejected; after a few rejections the sweep takes over too.
            self._candidate = self._hint.update(
                gray, frame.t, tag.pan_deg, tag.tilt_deg, self._tracker.config.min_radius_px
            )
        return False

    def _head_shift(
        self,
        frame: Frame,
        at_px: tuple[float, float],
        head_from: tuple[float, float],
        head_to: tuple[float, float],
    ) -> tuple[float, float]:
        """The image motion of a world-fixed point at ``at_px`` as the head turns between two
        frames' tags (dffd.core.geometry.image_shift)."""
        h, w = frame.image.shape[:2]
        return image_shift(at_px, (w, h), self.lens.focal_length_px, head_from, head_to)

    def _seed_velocity(self, frame: Frame, tag: FrameTag) -> None:
        """A contour just started: a target seen shortly before starts with the velocity between
        the two sightings (ContourTracker.seed_velocity)."""
        seen = self._last_seen
        if not self.config.compensate_head_motion or seen is None:
            return
        t_seen, c_seen, head_seen = seen
        if not 0.0 < frame.t - t_seen <= REACQUIRE_VELOCITY_GAP_S:
            return
        shift = self._head_shift(frame, c_seen, head_seen, (tag.pan_deg, tag.tilt_deg))
        self._tracker.seed_velocity(t_seen, c_seen, shift)

    # -- estimation -------------------------------------------------------------------------
    def _reset_estimators(self) -> None:
        self._reset_filters_keep_tracking()
        self._bursts.reset()

    def _reset_filters_keep_tracking(self) -> None:
        cfg = self.config
        self._bank.reset()
        self._diff = Differentiator(cfg.differentiator_omega)
        self._vel_cam = VelocityEstimator(cfg.differentiator_omega / 3)
        self._vel_world = VelocityEstimator(cfg.differentiator_omega / 3)
        self._pending: Measurement | None = None
        self._pending_t0: float | None = None  # its first frame's time
        self._prev: tuple[float, float] | None = None  # (t, s) of the last frame with a size
        self._sizes = SizeHistory(SIZE_HISTORY_FRAMES)
        prior = cfg.size_offset_prior_px
        self._offset = (
            None
            if prior is None
            else SizeOffset(prior * self.lens.pixel_pitch_mm / self.lens.focal_length_mm)
        )
        self._f_img: float | None = None  # image distance at the last known focus setting
        self._last_measured: float | None = None
        self._prev_pos_t: float | None = None
        self._diff_rate: float | None = None  # filtered ρ̂ = ṡ/s at the last frame
        self._good_t: float | None = None  # time of the last measured (used) size

    def _image_distance_mm(self, counts: int) -> float:
        if self.config.magnification == "pinhole":
            return self.lens.focal_length_mm
        return self._settings.v_mm(counts)

    def _depth(self, name: EstimatorName) -> float | None:
        if name == "measured":
            return self._last_measured if self._bank.initialised else None
        return self._bank.depth(name)

    def _finish_burst(self) -> Measurement | None:
        """Fit the pending burst; an accepted one is applied at the next tracking frame."""
        m = self._bursts.finish(self._log_size_ratios, self._depth(self.config.best))
        if m is not None and m.accepted:
            self._pending = m
            self._pending_t0 = self._bursts.last_t_first
        return m

    def _frame_estimate(
        self, frame: Frame, tag: FrameTag, obs: BoundaryObservation
    ) -> tuple[Estimate, Measurement | None]:
        """Step every estimator to this frame with its size; a tracking frame (the burst's
        compensation wants the sizes after it) also fits the pending burst and applies it."""
        cfg = self.config
        t = frame.t
        if self._prev is not None and t - self._prev[0] > cfg.max_gap_s:
            self._reset_filters_keep_tracking()
        if tag.focus_counts is not None:
            self._f_img = self._image_distance_mm(tag.focus_counts)
        # A transit frame's focus setting is unknown: the last known one's image distance (the
        # focal length itself under the default pinhole magnification).
        f_img = self._f_img if self._f_img is not None else self.lens.focal_length_mm
        dt = 0.0 if self._prev is None else t - self._prev[0]
        s_meas = obs.r_px * self.lens.pixel_pitch_mm / f_img  # = R / z
        if self._prev is not None and dt > 0 and not self._size_usable(obs, tag, s_meas, dt):
            # No size from this frame (too blurred, or off the track: _size_usable): the size
            # is held, and the next measured size telescopes the ratio over the gap.
            s = self._prev[1]  # held: extrapolating on the rate drifted (11 % on start-up)
            sdot = 0.0
        else:
            s = s_meas
            self._good_t = t
            _, sdot = self._diff.update(s, dt)
            self._diff_rate = sdot / s if dt > 0 else None  # ρ̂ = ṡ/s, filtered
            self._sizes.add(t, s)
        rho: float | None = None
        if self._prev is not None and dt > 0:
            rho = math.log(s / self._prev[1]) / dt
        self._last_measured = None
        measured_t: float | None = None
        done = self._finish_burst() if tag.role == "track" else None
        bank = self._bank
        d = self._size_offset()  # the estimators see the size without the offset
        if bank.initialised and self._prev is not None and dt > 0:
            bank.predict(dt, s - d, self._prev[1] - d, sdot, rho if rho is not None else 0.0)
        pending, self._pending = self._pending, None
        if pending is not None and pending.z_m is not None and pending.sigma_m is not None:
            s_b = self._size_at(pending.t + cfg.measurement_time_offset_s, self._pending_t0, s)
            bank.correct(pending, s_b - d, s - d, self._diff_rate or 0.0)
            if self._offset is not None:
                self._offset.add(pending.z_m, pending.sigma_m, s_b)
            self._last_measured = pending.z_m
            measured_t = pending.t
        self._prev = (t, s)
        estimate = self._make_estimate(
            frame, tag, obs, s=s - d, rho=rho, measured_t=measured_t, f_img=f_img
        )
        return estimate, done

    def _size_offset(self) -> float:
        """The size offset d = δ p/F removed from every size (0 without the offset state)."""
        est = None if self._offset is None else self._offset.estimate()
        return 0.0 if est is None else est[0]

    def _on_size_jump(self, obs: BoundaryObservation, jump_ln: float) -> None:
        """A depth jump: nothing is interpolated across it (bursts, transport, the rate)."""
        logger.info("size jump of %+.1f %% (r %.1f px): no burst across", 100 * jump_ln, obs.r_px)
        reason = "depth jump during the burst"
        self._bursts.reject_pending(reason)
        if self._pending is not None:  # fitted before the jump, transported after it
            self._bursts.rejections[reason] += 1
            self._pending = None
        self._bursts.reset()
        self._sizes.clear()
        self._diff = Differentiator(self.config.differentiator_omega)

    def _size_usable(self, obs: BoundaryObservation, tag: FrameTag, s: float, dt: float) -> bool:
        """Whether the frame's size ``s`` is used.

        Not when its edge profile (``edge_sigma_px``, the log-parabola width of the gradient
        peak) does not fit ``SIZE_EDGE_WIDTHS`` times within the normal lines, where the
        curvature correction of r fails (docs/estimation.md §11). Not when ``ln s`` is off the
        filtered rate's prediction by more than ``size_jump_ln`` on a burst or transit frame
        (blurred frames of the brackets were 3-35 % off), nor on a tracking frame defocused by
        more than ``SIZE_JUMP_MAX_BLUR_PX`` for the predicted depth (one held at a bracket's
        end: :meth:`_defocused`); on a tracking frame at the best focus of a known depth that
        is a depth jump (:meth:`_on_size_jump`), and the size is used.
        """
        w = obs.edge_sigma_px
        if math.isfinite(w) and SIZE_EDGE_WIDTHS * w > self.config.search_px:
            return False
        if self._prev is None or self._diff_rate is None or self._good_t is None:
            return True
        gap = self._prev[0] + dt - self._good_t  # since the last measured size
        if gap > SIZE_JUMP_MAX_GAP_S:
            return True  # the rate's prediction is too uncertain to call a jump
        off = math.log(s) - (math.log(self._prev[1]) + self._diff_rate * gap)
        if abs(off) <= self.config.size_jump_ln:
            return True
        if tag.role != "track" or not self._bank.initialised or self._defocused(tag):
            return False
        self._on_size_jump(obs, off)
        return True

    def _defocused(self, tag: FrameTag) -> bool:
        """The frame's focus setting blurs the target at the predicted depth by more than
        ``SIZE_JUMP_MAX_BLUR_PX`` (its size is then as off as a bracket end's, not a jump)."""
        z = self._depth(self.config.best)
        if tag.focus_counts is None or z is None or not z > 0:
            return False
        lens = self.lens
        n_f = lens.f_number if lens.f_number is not None else self.config.plan.default_f_number
        v_sharp = lens.v_from_depth(max(z, 2 * lens.focal_length_mm / 1000.0))
        blur = lens.blur_radius_px(self._settings.v_mm(tag.focus_counts), v_sharp, n_f)
        return blur > SIZE_JUMP_MAX_BLUR_PX

    def _log_size_ratios(self, times: list[float], t_mid: float) -> list[float] | None:
        """ln(s(t_i)/s(t_mid)) for burst frames, from the line through the sizes of the frames
        from the burst's first to now (:meth:`SizeHistory.line`); None without two of them (no
        compensation then)."""
        if not self.config.compensate_burst_motion:
            return None
        line = self._sizes.line(min(times), math.inf)
        if line is None:
            return None
        slope = line[2]
        return [slope * (ti - t_mid) for ti in times]

    def _size_at(self, t_b: float, t_first: float | None, s_now: float) -> float:
        """Normalised size at the burst time ``t_b`` from the line through the sizes of the
        frames from the burst's first (``t_first``) to now."""
        if not self.config.transport_measurements or t_first is None:
            return s_now
        line = self._sizes.line(t_first, math.inf)
        if line is None:
            return s_now
        t_ref, ln_ref, slope = line
        return math.exp(ln_ref + slope * (t_b - t_ref))

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
        bank = self._bank
        # {name: self._depth(name)} for ESTIMATORS, in their order, in one call (every frame
        # with a contour): none before the bank's first burst
        depth = bank.depths(self._last_measured)
        sigma_by = bank.sigmas(depth)
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
            beta_m_s=bank.cf2.beta if bank.initialised else None,
            lpv_b_m_s=bank.lpv.b if bank.initialised else None,
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
