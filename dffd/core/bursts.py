"""Burst assembly: the focus cost of burst frames, gathered into bursts and fitted (pure).

A burst is three (or more) frames at known focus settings bracketing the sharp setting. Each
burst frame's focus cost (``focus_measure``: the paper's cost (2), or the edge second moment) is
taken along the contour's normals; when the pipeline closes the burst (at the next tracking frame,
or when another burst id arrives) the parabola is fitted, each setting first shifted by the
target's motion during the burst, and a :class:`~dffd.core.outputs.Measurement` is made.

*Rolling* bursts (the scheduler's triangle lo, mid, hi, mid, lo, …) tag each end frame alone
(the last slot, none before it): such a frame closes a burst made of the previous end on the
other side of the bracket, the last tracking frame between the two (at the middle: tracking
frames carry their cost too) and itself. A burst left with fewer than three frames with a cost is
not emitted; it is counted in :attr:`BurstAssembler.rejections` with its reason. A burst one of
whose frames has no edge-moment cost (its blur overflows the normal lines: the first, full-range
brackets) is fitted with (2) on all its frames and counted in
:attr:`BurstAssembler.measure_fallbacks`. See docs/estimation.md §1.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace

from dffd.core.combine import PeakBias, combine_vertices
from dffd.core.contour import BoundaryObservation
from dffd.core.focus import BurstFit, FitConfig, fit_burst, frame_cost
from dffd.core.lens import Lens, VertexResponse
from dffd.core.outputs import Measurement
from dffd.literals import FocusMeasure

__all__ = ["V_CACHE_ENTRIES", "BurstAssembler", "BurstSample", "FocusSettings"]

logger = logging.getLogger(__name__)

# Memoised focus settings (lens table look-ups): the counts of a session span a few thousand
# values at most; the cache is emptied when it reaches this size.
V_CACHE_ENTRIES = 4096
# A rolling burst is both ends of one bracket around its middle: the scheduler re-focuses the
# middle within a quarter of a bracket step of the plan's (sides up to 1.25/0.75 = 1.7 apart in
# v, plus the plan's drift between the two ends). Sides further apart are ends of two plans —
# on the demo, the full-range first burst's end with the next plan's middle and end, (7371, 7629,
# 10654) counts, sides 11x apart, fitted 1.7 m off and published as the first depth — so such an
# end opens a new sequence instead.
ROLLING_MAX_SIDE_RATIO = 3.0

# ln(s(t_i)/s(t_mid)) for a burst's frame times and mid-time, or None (no compensation).
LogSizeRatios = Callable[[list[float], float], "list[float] | None"]


class FocusSettings:
    """``lens.v_from_counts``, memoised: a PCHIP evaluation costs ~20 µs, and the scheduler
    returns to the same few focus settings frame after frame."""

    def __init__(self, lens: Lens) -> None:
        self.lens = lens
        self._v: dict[int, float] = {}

    def v_mm(self, counts: int) -> float:
        """Lens-to-sensor distance (mm) at the focus setting ``counts``."""
        v = self._v.get(counts)
        if v is None:
            if len(self._v) >= V_CACHE_ENTRIES:
                self._v.clear()
            v = self._v[counts] = self.lens.v_from_counts(counts)
        return v


@dataclass(slots=True)
class BurstSample:
    """One frame's focus cost at a known setting."""

    index: int
    t: float
    counts: int
    v_mm: float
    g: float  # cost of the configured measure (NaN: none on this frame)
    sigma_g: float
    peak: tuple[float, float] | None  # cost (2) when the measure is another one (its fallback)


class BurstAssembler:
    """Collects burst frames' costs into bursts and fits them (see the module docstring)."""

    def __init__(
        self,
        settings: FocusSettings,
        *,
        fit: FitConfig,
        focus_measure: FocusMeasure,
        trim_fraction: float,
        burst_size: int,
        rolling_max_span_s: float,
        vertex_response: bool,
    ) -> None:
        self.settings = settings
        self.lens = settings.lens
        self.fit = fit
        self.focus_measure: FocusMeasure = focus_measure
        # The calibration's vertex response corrects the vertex of bursts fitted with the
        # measure it was measured with (docs/estimation.md §21); "debiased_peak" combines two
        # measures' vertices and is not corrected.
        response = self.lens.vertex_response
        self.response: VertexResponse | None = (
            response
            if vertex_response
            and response is not None
            and response.measure == focus_measure
            and focus_measure != "debiased_peak"
            else None
        )
        self.trim_fraction = trim_fraction
        self.burst_size = burst_size
        self.rolling_max_span_s = rolling_max_span_s
        # Bursts not emitted (fewer than three frames), by reason.
        self.rejections: Counter[str] = Counter()
        # Bursts fitted with cost (2) because a frame had no cost of the configured measure.
        self.measure_fallbacks = 0
        self._samples: list[BurstSample] = []
        self._id: int | None = None
        self._last_end: BurstSample | None = None  # the last rolling end (the next one's slot 0)
        self._last_mid: BurstSample | None = None  # the last tracking frame's cost sample
        # the last tracking frame while its cost is not taken yet (see set_middle)
        self._mid_frame: tuple[int, float, int, BoundaryObservation] | None = None
        # the peak gradient's bias against the edge moment (measure "debiased_peak"); a property
        # of the lens and the measures, kept across targets
        self.peak_bias = PeakBias()
        # time of the first frame of the last burst fitted (the sizes from there on transport it)
        self.last_t_first: float | None = None

    @property
    def pending_id(self) -> int | None:
        """Id of the burst being gathered, or None."""
        return self._id

    def reset(self) -> None:
        """Drop the pending burst and the rolling sequence (a new target, a lost one)."""
        self.discard()
        self._last_end = None
        self._last_mid = None
        self._mid_frame = None

    def discard(self) -> None:
        """Drop the pending burst."""
        self._samples = []
        self._id = None

    def add(self, index: int, t: float, counts: int, burst: tuple[int, int] | None,
            obs: BoundaryObservation) -> None:  # fmt: skip
        """A burst frame (``burst`` = (id, slot) from its tag) at focus ``counts``."""
        bid, slot = burst if burst is not None else (-1, 0)
        sample = self.cost_sample(index, t, counts, obs)
        if self._id is None and slot == self.burst_size - 1 and slot > 0:
            self._add_rolling_end(bid, sample)
            return
        if self._id is None:
            self._id = bid
        if sample is not None:
            self._samples.append(sample)

    def set_middle(self, index: int, t: float, counts: int, obs: BoundaryObservation) -> None:
        """A tracking frame: at the best focus, the middle of the next rolling burst.

        Its cost is taken only when a rolling end closes a burst on it (:meth:`_middle`): on the
        bench's paper-circle run half of the tracking frames are followed by another before that.
        """
        self._mid_frame = (index, t, counts, obs)
        self._last_mid = None

    def cost_sample(
        self, index: int, t: float, counts: int, obs: BoundaryObservation
    ) -> BurstSample | None:
        """The frame's cost of the configured measure (and of (2) as its fallback), or None."""
        trim = self.trim_fraction
        measure: FocusMeasure = self.focus_measure
        cost = frame_cost(obs, measure, trim)
        peak = None if measure == "peak_gradient" else frame_cost(obs, "peak_gradient", trim)
        if cost is None and peak is None:
            return None
        g, sigma_g = (math.nan, math.nan) if cost is None else cost
        return BurstSample(index, t, counts, self.settings.v_mm(counts), g, sigma_g, peak)

    def finish(
        self, log_size_ratios: LogSizeRatios, z_fallback: float | None
    ) -> Measurement | None:
        """Fit the pending burst, or None when there is none or it is not a burst (counted).

        ``log_size_ratios`` gives each frame's size relative to the mid-time (the target's motion
        during the burst); ``z_fallback`` is the depth the compensation is computed at when the
        uncompensated fit is rejected.
        """
        if self._id is None:
            return None
        samples, bid = self._samples, self._id
        self.discard()
        if len(samples) < 3:
            # Not a burst (a claimed frame was dropped, the contour failed on a slot, the link
            # cut it short): nothing to fit and nothing the ``…/measurement`` schema accepts.
            self._reject(bid, f"{len(samples)} of 3 frames with a focus cost")
            return None
        self.last_t_first = min(s.t for s in samples)
        t_sum = 0.0
        for s in samples:  # sequential sum (as np.mean of a few values), no array
            t_sum += s.t
        t_mid = t_sum / len(samples)
        fell_back = False
        if any(math.isnan(s.g) for s in samples):
            # one frame's blur overflowed the edge-moment window: the whole burst on cost (2)
            if any(s.peak is None for s in samples):
                self._reject(bid, "a frame without a focus cost")
                return None
            samples = [replace(s, g=s.peak[0], sigma_g=s.peak[1]) for s in samples if s.peak]
            self.measure_fallbacks += 1
            fell_back = True
        v = [s.v_mm for s in samples]
        g = [s.g for s in samples]
        sg = [s.sigma_g for s in samples]
        log_ratio = log_size_ratios([s.t for s in samples], t_mid)
        # a burst that fell back to cost (2) is not in the response's measure
        response = None if fell_back else self.response
        fit = self._fit(v, g, sg, log_ratio, z_fallback, response=response)
        if self.focus_measure == "debiased_peak":
            fit = self._combine(fit, v, samples, log_ratio, z_fallback, fallback=fell_back)
        if not fit.accepted:
            logger.debug("burst %d rejected: %s", bid, fit.reason)
        return Measurement(
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

    def _fit(
        self,
        v: list[float],
        g: list[float],
        sg: list[float],
        log_ratio: list[float] | None,
        z_fallback: float | None,
        *,
        response: VertexResponse | None = None,
    ) -> BurstFit:
        """The parabola fit, each setting shifted by the target's motion during the burst (its
        vertex corrected by ``response``, :func:`dffd.core.focus.fit_burst`)."""
        fit = fit_burst(v, g, sg, self.lens, self.fit, response=response)
        if log_ratio is None:
            return fit
        z_ref = fit.z_m if fit.accepted else z_fallback
        for _ in range(2):  # the shift depends (weakly) on the depth it is computed at
            if z_ref is None or not z_ref > 0:
                break
            v_ref = self.lens.v_from_depth(z_ref)
            # z_i = z s(t_mid)/s(t_i): the sharp setting at frame i is v(z_i)
            v_comp = [
                vi - (self.lens.v_from_depth(z_ref * math.exp(-lr)) - v_ref)
                for vi, lr in zip(v, log_ratio, strict=True)
            ]
            fit = fit_burst(v_comp, g, sg, self.lens, self.fit, response=response)
            z_ref = fit.z_m if fit.accepted else None
        return fit

    def _combine(
        self,
        fit: BurstFit,
        v: list[float],
        samples: list[BurstSample],
        log_ratio: list[float] | None,
        z_fallback: float | None,
        *,
        fallback: bool,
    ) -> BurstFit:
        """``debiased_peak``: the peak-gradient fit of the same frames as the edge-moment fit
        ``fit``, less its bias against it (dffd.core.combine); a burst on cost (2) alone too."""
        mid, h = 0.5 * (min(v) + max(v)), 0.5 * (max(v) - min(v))
        if not h > 0:
            return fit
        if fallback:
            # cost (2) alone (the first, full-range brackets): as with edge_variance, unless the
            # bias fit has seen bursts to debias it with
            if not fit.accepted or self.peak_bias.count == 0:
                return fit
            b, var_b = self.peak_bias.correction(0.0)
            x = (fit.v_hat_mm - mid) / h - b
            return self._with_vertex(
                fit, mid + h * x, h * math.sqrt((fit.sigma_v_mm / h) ** 2 + var_b)
            )
        if not fit.accepted or any(s.peak is None for s in samples):
            return fit
        peaks = [s.peak for s in samples if s.peak is not None]
        pg = self._fit(v, [p[0] for p in peaks], [p[1] for p in peaks], log_ratio, z_fallback)
        if not pg.accepted:
            return fit
        x, var = combine_vertices(
            (fit.v_hat_mm - mid) / h,
            (fit.sigma_v_mm / h) ** 2,
            (pg.v_hat_mm - mid) / h,
            (pg.sigma_v_mm / h) ** 2,
            self.peak_bias,
        )
        return self._with_vertex(fit, mid + h * x, h * math.sqrt(var))

    def _with_vertex(self, fit: BurstFit, v_hat: float, sigma_v: float) -> BurstFit:
        """``fit`` with another vertex and its σ (depth and σ_z from the lens table)."""
        if v_hat <= self.lens.focal_length_mm:
            return fit
        z = self.lens.depth_from_v(v_hat)
        sigma_z = abs(self.lens.dz_dv(v_hat)) * sigma_v
        return replace(fit, v_hat_mm=v_hat, z_m=z, sigma_m=sigma_z, sigma_v_mm=sigma_v)

    def reject_pending(self, reason: str) -> None:
        """Drop the pending burst and count it with ``reason`` (e.g. a depth jump inside it)."""
        if self._id is not None:
            self._reject(self._id, reason)
            self.discard()

    def _add_rolling_end(self, bid: int, sample: BurstSample | None) -> None:
        """A last slot with none before it: a rolling end; close a burst with the previous end
        and the tracking frame between them (see the module docstring)."""
        prev = self._last_end
        self._last_end = sample
        if sample is None:
            return
        mid = None if prev is None else self._middle()
        if (
            prev is None
            or mid is None
            or not prev.t < mid.t < sample.t
            or sample.t - prev.t > self.rolling_max_span_s
            or (prev.counts - mid.counts) * (sample.counts - mid.counts) >= 0
            or not _one_bracket(prev, mid, sample)
        ):
            logger.debug("rolling burst %d opens a sequence (no previous end to close)", bid)
            return
        self._samples = [prev, mid, sample]
        self._id = bid

    def _middle(self) -> BurstSample | None:
        """The last tracking frame's cost sample (taken now if it was not yet)."""
        pending = self._mid_frame
        if pending is not None:
            self._mid_frame = None
            self._last_mid = self.cost_sample(*pending)
        return self._last_mid

    def _reject(self, bid: int, reason: str) -> None:
        self.rejections[reason] += 1
        logger.debug("burst %d rejected: %s", bid, reason)


def _one_bracket(prev: BurstSample, mid: BurstSample, end: BurstSample) -> bool:
    """The two ends lie about as far from the middle in v (see ROLLING_MAX_SIDE_RATIO)."""
    a, b = abs(prev.v_mm - mid.v_mm), abs(end.v_mm - mid.v_mm)
    return max(a, b) <= ROLLING_MAX_SIDE_RATIO * min(a, b)
