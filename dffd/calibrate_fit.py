"""The fits of ``dffd calibrate``: the sharpest setting of one sweep, the smooth focus model,
the lens table fitted through the depth points.

Pure numerics (no rig, no I/O), shared by the lab procedure and ``--sim`` (:mod:`dffd.calibrate`).

Vertex of one sweep (:func:`fit_vertex`). The costs at each setting are averages of several
frames (σ from their spread). The parabola is fitted on a window *symmetric about the vertex*
that reaches out to where the cost has risen by :data:`WINDOW_RISE` × its minimum — the blur of a
burst's outer settings (~3 px), where a focus cost is still parabolic in ``v``, and far enough
out that a flat bottom (a blur below a pixel changes no measure) or a local wiggle cannot pull
the vertex. The window is re-centred on the fitted vertex until it stops moving (an off-centre
window of a cost that is not exactly a parabola biases the vertex); points more than
:data:`OUTLIER_SIGMA` robust σ off the parabola are dropped. The sweep's settings are in counts;
the fit runs in whatever axis it is given — ``v`` through the provisional focus model on the
second pass, as the estimator's own burst fit does.

Focus model (:func:`fit_focus_model`). The thin lens turns each depth z into a focus power
``P = 1/z`` (dioptres); the lens's focus cam makes ``P`` a smooth monotone function of counts.
``P(u)`` is a polynomial in the normalised counts ``u``; its degree is chosen by leave-one-out
cross-validation (the degree that best predicts each depth from the others), outliers beyond
:data:`OUTLIER_SIGMA` robust σ are dropped, and the residuals are reported in v (µm) and in
depth (mm). ``v(counts) = 1 / (1/f − P/1000)`` is then tabulated densely for the lens file.

Lens table (:func:`fit_table`). The depth points of the sweeps (:class:`DepthPoint`) and the
infinity anchor at the far end of the focus range give the model; each vertex is refitted in
``v`` through it (on the estimator's burst bracket) and the model refitted; the table is the
model every :data:`TABLE_STEP_COUNTS` over the focus range where it stays monotone. With fewer
than :data:`MIN_MODEL_DEPTHS` depths the table is the points themselves (:func:`lens_from_points`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, make_smoothing_spline

from dffd.core.focus import PlanConfig
from dffd.core.lens import MM_PER_M, Lens

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

# The window reaches out to where the cost has risen by this fraction of its minimum: about the
# blur of the estimator's outer burst settings (PlanConfig.outer_blur_px = 3 px) with either
# measure on a 0.5–0.7 px residual blur, where the cost is still parabolic in v.
WINDOW_RISE = 1.0
MIN_WINDOW_POINTS = 5  # fewer settings in the window: fall back to the ±FALLBACK points
FALLBACK_HALF_POINTS = 3
CENTRE_ITERATIONS = 8  # re-centring passes (converges in 2-3)
OUTLIER_SIGMA = 4.0  # robust σ beyond which a point is dropped (a frame with a lost contour …)
MAD_TO_SIGMA = 1.4826  # σ of a normal distribution per median absolute deviation
MIN_POINTS_PER_COEF = 1  # points beyond the coefficients needed for a leave-one-out choice
MAX_OUTLIER_FRACTION = 0.2  # never drop more than this fraction of the depths
SPLINE_MIN_POINTS = 6  # a residual spline needs this many depths (scipy: at least 5)
MAX_BASE_DEGREE = 3  # the polynomial under the spline: at most cubic (the spline does the rest)
TABLE_STEP_COUNTS = 256  # spacing of the written table's rows (PCHIP of a smooth model: exact)
# Half-width of the vertex window of the refit in v, in px of blur radius: the estimator's own
# burst bracket (PlanConfig.outer_blur_px, 3 px), where a measure's lean on a lens is the one its
# bursts fit. Chosen on the reference optics (paper-circle seed 1, 60 s, peak_gradient): 1 px ->
# table 14 mm rms, bench 28 mm; 3 px -> 3.6 mm, 8.8 mm (true table: 8.0 mm). On the aberrated
# optics the bench is the same with 1 or 3 px (docs/estimation.md §10).
VERTEX_WINDOW_BLUR_PX = PlanConfig().outer_blur_px
REFIT_PASSES = 2  # vertex refits in v through the latest model (the second moves < 0.1 µm)
MIN_MODEL_DEPTHS = 4  # fewer depths: the table is the measured points themselves
# Repeated sweeps of one depth (combine_sweeps): with three or more, a sweep whose vertex is more
# than this many of its σ from the others' median is dropped (a disturbed sweep: the target
# knocked, a lighting flicker); the combined σ is scaled up by the sweeps' own disagreement.
SWEEP_OUTLIER_SIGMA = 4.0


class CalibrationError(RuntimeError):
    """No sharp setting found (target not found, flat cost, …) or no monotone table fitted."""


@dataclass(frozen=True, slots=True)
class DepthPoint:
    """The sharpest focus setting found for one known depth."""

    z_m: float
    counts: int
    v_mm: float
    cost_min: float
    counts_exact: float = math.nan  # the vertex before rounding (NaN: ``counts``)
    sigma_counts: float = math.nan  # its σ from the fit (NaN: unknown)
    # the fine sweep: settings (counts), mean cost, σ of the mean (for the refit in v)
    sweep: tuple[tuple[float, float, float], ...] = ()
    n_sweeps: int = 1  # sweeps of this depth combined into this point (combine_sweeps)
    spread_counts: float = math.nan  # their vertices' standard deviation (NaN: one sweep)
    sweeps_chi2: float = math.nan  # their χ² per degree of freedom about the mean (NaN: one)

    @property
    def at(self) -> float:
        """The sharpest counts, unrounded."""
        return self.counts if math.isnan(self.counts_exact) else self.counts_exact


@dataclass(frozen=True, slots=True)
class VertexFit:
    """The sharpest setting of one sweep: the vertex, its σ and the window it was fitted on."""

    x: float
    sigma: float
    window: tuple[float, float]
    n_used: int
    n_dropped: int


@dataclass(frozen=True, slots=True, eq=False)
class FocusModel:
    """Focus power P(u) = Σ coef_k u^k + s(u) (dioptres) of the normalised counts u ∈ [0, 1]:
    a low-order polynomial and a smoothing spline of its residuals (None: the polynomial), held
    at its end values beyond the depths it was fitted to (the polynomial extrapolates)."""

    coef: tuple[float, ...]  # lowest degree first
    counts_lo: float
    counts_hi: float
    focal_length_mm: float
    spline: BSpline | None = None
    spline_u: tuple[float, float] = (0.0, 1.0)  # the range of u the spline was fitted over

    @property
    def degree(self) -> int:
        """Polynomial degree."""
        return len(self.coef) - 1

    def power_dpt(self, counts: npt.ArrayLike) -> FloatArray:
        """Focus power (1/z of the depth in focus, dioptres) at ``counts``."""
        u = (np.asarray(counts, dtype=np.float64) - self.counts_lo) / (
            self.counts_hi - self.counts_lo
        )
        p = np.polynomial.polynomial.polyval(u, self.coef)
        if self.spline is not None:
            p = p + self.spline(np.clip(u, *self.spline_u))
        return np.asarray(p, dtype=np.float64)

    def v_mm(self, counts: npt.ArrayLike) -> FloatArray:
        """Lens-to-sensor distance v at ``counts`` (thin lens: 1/v = 1/f − P)."""
        return 1.0 / (1.0 / self.focal_length_mm - self.power_dpt(counts) / MM_PER_M)

    def counts_for_v(self, v_mm: float, lo: float, hi: float) -> float:
        """The counts in [lo, hi] where the model gives ``v_mm`` (bisection: P is monotone)."""
        target = (1.0 / self.focal_length_mm - 1.0 / v_mm) * MM_PER_M
        p_lo, p_hi = (float(x) for x in self.power_dpt([lo, hi]))
        rising = p_hi > p_lo
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if (float(self.power_dpt(mid)) < target) == rising:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)


@dataclass(frozen=True, slots=True)
class ModelFit:
    """The focus model and how well it fits the depths it was fitted to."""

    model: FocusModel
    used: tuple[bool, ...]  # per depth: False where rejected as an outlier
    residual_v_um: tuple[float, ...]  # per depth: measured v − model v at its counts
    residual_depth_mm: tuple[float, ...]  # per depth: model depth at its counts − z
    loo_rms_v_um: float  # leave-one-out prediction error of the chosen degree

    @property
    def rms_v_um(self) -> float:
        """RMS v residual over the depths used."""
        r = np.asarray(self.residual_v_um)[np.asarray(self.used)]
        return float(np.sqrt(np.mean(r * r)))

    @property
    def table_sigma_v_um(self) -> float:
        """Standard error of the fitted model's v over the calibrated depths: for a linear
        smoother with p effective parameters on n depths, E[residual²] = σ²(1 − p/n) and
        E[leave-one-out²] ≈ σ²(1 + p/n), so the model's own error σ² p/n ≈ (loo² − res²)/2."""
        return math.sqrt(max(self.loo_rms_v_um**2 - self.rms_v_um**2, 0.0) / 2.0)

    @property
    def rms_depth_mm(self) -> float:
        """RMS depth residual over the depths used."""
        r = np.asarray(self.residual_depth_mm)[np.asarray(self.used)]
        return float(np.sqrt(np.mean(r * r)))


@dataclass(frozen=True, slots=True)
class TableFit:
    """The calibrated table: the depth points, the smooth model and its residuals."""

    points: tuple[DepthPoint, ...]
    fit: ModelFit | None  # None with fewer than MIN_MODEL_DEPTHS depths
    lens: Lens

    def residual_lines(self) -> list[str]:
        """One line per depth: the sharpest counts, v and the model's residual (for the CLI)."""
        lines = []
        for i, p in enumerate(self.points):
            line = f"z = {p.z_m:6.2f} m  sharpest counts {p.at:9.1f}"
            if not math.isnan(p.sigma_counts):
                line += f" ± {p.sigma_counts:5.1f}"
            line += f"  v = {p.v_mm:.6f} mm"
            if self.fit is not None:
                line += (
                    f"  model residual {self.fit.residual_v_um[i]:+6.3f} µm of v, "
                    f"{self.fit.residual_depth_mm[i]:+7.1f} mm of depth"
                )
                if not self.fit.used[i]:
                    line += "  REJECTED (outlier: re-measure this depth)"
            lines.append(line)
        if self.fit is not None:
            m = self.fit
            lines.append(
                f"focus model: P(counts) polynomial of degree {m.model.degree}"
                f"{' + smoothing spline' if m.model.spline is not None else ''} (leave-one-out), "
                f"{sum(m.used)} of {len(m.used)} depths; residual rms "
                f"{m.rms_v_um:.3f} µm of v, {m.rms_depth_mm:.1f} mm of depth; leave-one-out "
                f"prediction rms {m.loo_rms_v_um:.3f} µm of v"
            )
        return lines


class FocusOptics(Protocol):
    """What a table is fitted for: the optics at a fixed zoom and the focus range."""

    focal_length_mm: float
    pixel_pitch_mm: float
    zoom_counts: int | None
    focus_range: tuple[int, int]  # far end … near end, counts


def fit_vertex(
    x: FloatArray, g: FloatArray, sigma_g: FloatArray, half_width: float | None = None
) -> VertexFit | None:
    """Vertex of the costs ``g`` (σ ``sigma_g``) at the settings ``x`` (sorted), or None.

    ``half_width``: the window's half-width in ``x`` (the estimator's bracket); None: out to
    where the cost has risen by WINDOW_RISE on the nearer side.
    """
    ok = np.isfinite(g) & np.isfinite(sigma_g)
    x, g, s = x[ok], g[ok], np.maximum(sigma_g[ok], 1e-12)
    if len(x) < 3:
        return None
    keep = np.ones(len(x), dtype=bool)
    centre = float(x[int(np.argmin(g))])
    fit = None
    for _ in range(CENTRE_ITERATIONS):
        sel = _window(x, g, keep, centre, half_width)
        fit = _parabola(x[sel], g[sel], s[sel])
        if fit is None:
            return None
        resid = (g[sel] - _eval(fit, x[sel])) / s[sel]
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(resid - np.median(resid)))), 1.0)
        bad = np.flatnonzero(sel)[np.abs(resid) > OUTLIER_SIGMA * scale]
        if len(bad):
            keep[bad] = False
            continue
        vertex, _ = _vertex(fit)
        lo, hi = float(x[sel].min()), float(x[sel].max())
        vertex = min(max(vertex, lo), hi)
        if abs(vertex - centre) < 1e-3 * (hi - lo):
            centre = vertex
            break
        centre = vertex
    assert fit is not None
    sel = _window(x, g, keep, centre, half_width)
    fit = _parabola(x[sel], g[sel], s[sel])
    if fit is None:
        return None
    vertex, sigma = _vertex(fit)
    lo, hi = float(x[sel].min()), float(x[sel].max())
    if not lo <= vertex <= hi:
        return None
    return VertexFit(vertex, sigma, (lo, hi), int(sel.sum()), int((~keep).sum()))


def fit_focus_model(
    counts: FloatArray,
    z_m: FloatArray,
    sigma_counts: FloatArray,
    focal_length_mm: float,
    counts_span: tuple[float, float],
) -> ModelFit:
    """P(counts) through the depths' sharpest counts; degree by leave-one-out, outliers dropped.

    ``counts_span`` normalises the counts (the focus range: far end, near end).
    """
    power = 1.0 / np.asarray(z_m, dtype=np.float64)
    lo, hi = counts_span
    u = (np.asarray(counts, dtype=np.float64) - lo) / (hi - lo)
    sigma_p = _power_sigma(u, power, np.asarray(sigma_counts, dtype=np.float64), hi - lo)
    used = np.ones(len(u), dtype=bool)
    max_drop = int(MAX_OUTLIER_FRACTION * len(u))
    while True:
        model, loo = _fit_model(u[used], power[used], sigma_p[used], (lo, hi), focal_length_mm)
        resid = (power - model.power_dpt(counts)) / sigma_p
        r_used = resid[used]
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(r_used - np.median(r_used)))), 1.0)
        worst = int(np.argmax(np.where(used, np.abs(resid), -np.inf)))
        if abs(resid[worst]) <= OUTLIER_SIGMA * scale or (~used).sum() >= max_drop:
            break
        used[worst] = False
    v_meas = 1.0 / (1.0 / focal_length_mm - power / MM_PER_M)
    v_model = model.v_mm(counts)
    with np.errstate(divide="ignore", invalid="ignore"):  # a depth at infinity: P = 0
        z_model = 1.0 / model.power_dpt(counts)
        dz_mm = np.nan_to_num((z_model - z_m) * MM_PER_M)
    dv_dp = v_meas**2 / MM_PER_M  # mm per dioptre
    return ModelFit(
        model,
        tuple(bool(b) for b in used),
        tuple(float(x) for x in (v_meas - v_model) * 1e3),
        tuple(float(x) for x in dz_mm),
        float(loo * float(np.median(dv_dp)) * 1e3),
    )


def fit_table(
    name: str,
    rig: FocusOptics,
    points: list[DepthPoint],
    f_number: float | None = None,
    window_blur_px: float = VERTEX_WINDOW_BLUR_PX,
) -> TableFit:
    """The calibrated lens: a smooth focus model through the depth points (vertices refitted in
    v through it, on ± ``window_blur_px`` of blur), tabulated densely; with fewer than
    MIN_MODEL_DEPTHS depths, the points themselves."""
    f, pitch = rig.focal_length_mm, rig.pixel_pitch_mm
    groups = _by_depth(points)
    points = [combine_sweeps(g) for g in groups]
    if len(points) < MIN_MODEL_DEPTHS:
        lens = lens_from_points(name, f, pitch, points)
        return TableFit(tuple(points), None, _with_f_number(lens, f_number, rig.zoom_counts))
    _check_monotone(points)
    span = (float(rig.focus_range[0]), float(rig.focus_range[1]))
    # The model is anchored at P = 0 at the far end of the focus range (focus at infinity, the
    # VISCA camera's datasheet, docs/design.md §6): the estimator's brackets at 10 m reach far
    # past the last calibrated depth, and there an unanchored model's cam ripple is free
    # (aberrated optics, seed 1: a true 100 m read as 44 m; bench 771 -> 483 mm ss RMS on 60 s,
    # true table 481 mm; reference unchanged).
    model = _fit_anchored(points, f, span)
    # Second pass: each vertex refitted in v through the model (the estimator fits its bursts
    # in v; a parabola in counts leans where the cam curves), then the model refitted. The axis
    # is the model's polynomial without its residual spline: a spline that follows the first
    # pass's scattered vertices warps each sweep's axis and feeds the scatter back (reference
    # optics seed 2: refitted vertices ±1.9 µm off the same sweeps fitted on the true axis, table
    # 26 mm rms; through the polynomial ±0.2 µm, 5 mm).
    n_f = f_number if f_number is not None else PlanConfig().default_f_number
    per_px = pitch * n_f * 2.0 / f  # mm of v per px of blur radius, per mm of v (plan_burst)
    refit = points
    for _ in range(REFIT_PASSES):
        mapping = dataclasses.replace(model.model, spline=None)
        refit = [
            combine_sweeps([_refit_in_v(p, mapping, window_blur_px * per_px * p.v_mm) for p in g])
            for g in groups
        ]
        model = _fit_anchored(refit, f, span)
    grid, v = _tabulate(model.model, (min(p.at for p in refit), max(p.at for p in refit)), span)
    lens = Lens(
        name, f, pitch, tuple(int(c) for c in grid), tuple(float(x) for x in v),
        f_number=f_number, zoom_counts=rig.zoom_counts,
        table_sigma_v_mm=model.table_sigma_v_um / 1000.0,
    )  # fmt: skip
    return TableFit(tuple(refit), model, lens)


def lens_from_points(
    name: str, focal_length_mm: float, pixel_pitch_mm: float, points: list[DepthPoint]
) -> Lens:
    """A :class:`Lens` from the sweep results; raises CalibrationError if not monotone."""
    _check_monotone(points)
    pts = sorted(points, key=lambda p: p.counts)
    counts = [p.counts for p in pts]
    v = [p.v_mm for p in pts]
    return Lens(name, focal_length_mm, pixel_pitch_mm, tuple(counts), tuple(v))


def combine_sweeps(sweeps: list[DepthPoint]) -> DepthPoint:
    """One point from repeated sweeps of one depth: the inverse-variance mean of their vertices
    (with three or more, a sweep beyond SWEEP_OUTLIER_SIGMA of the others' median dropped), its
    σ scaled by their disagreement when they scatter more than their σ says."""
    if len(sweeps) == 1:
        return sweeps[0]
    x = np.array([p.at for p in sweeps])
    sigma = np.array([p.sigma_counts for p in sweeps])
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, float(np.nanmedian(sigma)))
    if not np.isfinite(sigma).all():
        sigma = np.full(len(x), max(float(np.std(x)), 1.0))
    keep = np.ones(len(x), dtype=bool)
    if len(x) >= 3:
        off = np.abs(x - float(np.median(x))) / sigma
        worst = int(np.argmax(off))
        keep[worst] = off[worst] <= SWEEP_OUTLIER_SIGMA
    w = 1.0 / sigma[keep] ** 2
    mean = float(np.sum(w * x[keep]) / np.sum(w))
    dof = int(keep.sum()) - 1
    chi2 = float(np.sum(w * (x[keep] - mean) ** 2)) / dof if dof > 0 else 0.0
    sigma_mean = math.sqrt(1.0 / float(np.sum(w)) * max(chi2, 1.0))
    nearest = sweeps[int(np.argmin(np.where(keep, np.abs(x - mean), np.inf)))]
    return dataclasses.replace(
        nearest,
        counts=round(mean),
        counts_exact=mean,
        sigma_counts=sigma_mean,
        n_sweeps=len(sweeps),
        spread_counts=float(np.std(x, ddof=1)),
        sweeps_chi2=chi2,
    )


def model_with_structure(
    points: list[DepthPoint], f: float, span: tuple[float, float], like: FocusModel
) -> FocusModel:
    """The anchored focus model of ``like``'s structure (degree, spline or not) through
    ``points``, without choosing it again: for resampling the table's uncertainty."""
    counts, z, sigma_counts = _anchored_inputs(points, span)
    lo, hi = span
    u = (counts - lo) / (hi - lo)
    power = 1.0 / z
    sigma_p = _power_sigma(u, power, sigma_counts, hi - lo)
    return _build_model(
        u, power, sigma_p, span, f, degree=like.degree, spline=like.spline is not None
    )


# -- private helpers --------------------------------------------------------------------------
def _build_model(
    u: FloatArray,
    p: FloatArray,
    s: FloatArray,
    span: tuple[float, float],
    f: float,
    *,
    degree: int,
    spline: bool,
) -> FocusModel:
    """The weighted polynomial of ``degree`` through (u, p), plus a residual spline if asked."""
    base = FocusModel(tuple(float(c) for c in _polyfit(u, p, s, degree)), *span, f)
    return _with_spline(base, u, p, s) if spline else base


def _power_sigma(
    u: FloatArray, power: FloatArray, sigma_counts: FloatArray, width: float
) -> FloatArray:
    """σ of P from the vertex's σ in counts through the local slope of a first straight fit."""
    slope = abs(np.polyfit(u, power, 1)[0])
    return np.asarray(np.maximum(slope * np.asarray(sigma_counts) / width, 1e-9), dtype=np.float64)


def _fit_model(
    u: FloatArray, p: FloatArray, s: FloatArray, span: tuple[float, float], f: float
) -> tuple[FocusModel, float]:
    """Polynomial (degree by leave-one-out, at most MAX_BASE_DEGREE), with a residual spline
    where that predicts the left-out depths better; and its leave-one-out error (dioptres)."""
    degree, _ = _choose_degree(u, p, s, MAX_BASE_DEGREE)

    def build(mask: FloatArray, spline: bool) -> FocusModel:
        return _build_model(u[mask], p[mask], s[mask], span, f, degree=degree, spline=spline)

    best: tuple[float, bool] = (math.inf, False)
    everything = np.ones(len(u), dtype=bool)
    for spline in (False, True):
        errs = []
        for i in range(len(u)):
            mask = np.arange(len(u)) != i
            other = build(mask, spline)
            errs.append(float(other.power_dpt(u[i] * (span[1] - span[0]) + span[0])) - p[i])
        rms = math.sqrt(float(np.mean(np.square(errs))))
        if rms < best[0]:
            best = (rms, spline)
    return build(everything, best[1]), best[0]


def _with_spline(model: FocusModel, u: FloatArray, p: FloatArray, s: FloatArray) -> FocusModel:
    """``model`` plus a smoothing spline of its residuals, the smoothing chosen by generalised
    cross-validation (the cam's ripples the polynomial misses; none when they are noise)."""
    if len(u) < SPLINE_MIN_POINTS:
        return model
    order = np.argsort(u)
    r = p - model.power_dpt(u * (model.counts_hi - model.counts_lo) + model.counts_lo)
    spline = make_smoothing_spline(u[order], r[order], w=1.0 / s[order] ** 2)
    return FocusModel(
        model.coef, model.counts_lo, model.counts_hi, model.focal_length_mm, spline,
        (float(u.min()), float(u.max())),
    )  # fmt: skip


def _window(
    x: FloatArray, g: FloatArray, keep: BoolArray, centre: float, half_width: float | None
) -> BoolArray:
    """Settings within the symmetric half-width around ``centre`` (``half_width``, or where the
    cost has risen by WINDOW_RISE on the nearer side), never past either end of the sweep; at
    least MIN_WINDOW_POINTS of them."""
    gmin = float(g[keep].min())
    limit = gmin * (1.0 + WINDOW_RISE)
    half = math.inf if half_width is None else half_width
    for side in (x > centre, x < centre):
        beyond = keep & side & (g > limit)
        if half_width is None and beyond.any():
            reach = float(np.abs(x[beyond] - centre).min())
        else:
            reach = float(np.abs(x[keep & side] - centre).max()) if (keep & side).any() else 0.0
        half = min(half, reach)
    sel: BoolArray = keep & (np.abs(x - centre) <= half * (1 + 1e-9))
    if sel.sum() >= MIN_WINDOW_POINTS:
        return sel
    order = np.argsort(np.where(keep, np.abs(x - centre), np.inf))
    nearest: BoolArray = np.zeros(len(x), dtype=bool)
    nearest[order[: 2 * FALLBACK_HALF_POINTS + 1]] = True
    return nearest & keep


def _parabola(
    x: FloatArray, g: FloatArray, s: FloatArray
) -> tuple[FloatArray, FloatArray, float, float] | None:
    """Weighted fit g = a t² + b t + c, t = (x − m)/h: (coef, covariance, m, h), or None."""
    if len(x) < 3:
        return None
    m = float(x.mean())
    h = float(np.ptp(x)) / 2 or 1.0
    t = (x - m) / h
    design = np.stack([t * t, t, np.ones_like(t)], axis=1) / s[:, None]
    coef, *_ = np.linalg.lstsq(design, g / s, rcond=None)
    if coef[0] <= 0:
        return None
    resid = design @ coef - g / s
    dof = max(len(x) - 3, 1)
    chi2 = max(float(resid @ resid) / dof, 1.0)  # scale σ up when the points scatter more
    cov = np.asarray(np.linalg.pinv(design.T @ design) * chi2, dtype=np.float64)
    return np.asarray(coef, dtype=np.float64), cov, m, h


def _eval(fit: tuple[FloatArray, FloatArray, float, float], x: FloatArray) -> FloatArray:
    coef, _, m, h = fit
    t = (x - m) / h
    return np.asarray(coef[0] * t * t + coef[1] * t + coef[2], dtype=np.float64)


def _vertex(fit: tuple[FloatArray, FloatArray, float, float]) -> tuple[float, float]:
    """Vertex x and its σ (first-order propagation of the coefficient covariance)."""
    (a, b, _), cov, m, h = fit
    t0 = -b / (2 * a)
    grad = np.array([b / (2 * a * a), -1 / (2 * a)])
    var = float(grad @ cov[:2, :2] @ grad)
    return m + h * t0, h * math.sqrt(max(var, 0.0))


def _polyfit(u: FloatArray, p: FloatArray, s: FloatArray, degree: int) -> FloatArray:
    """Weighted least-squares polynomial (lowest degree first)."""
    design = np.vander(u, degree + 1, increasing=True) / s[:, None]
    coef, *_ = np.linalg.lstsq(design, p / s, rcond=None)
    return np.asarray(coef, dtype=np.float64)


def _choose_degree(
    u: FloatArray, p: FloatArray, s: FloatArray, max_degree: int
) -> tuple[int, float]:
    """The degree with the smallest leave-one-out prediction error (dioptres RMS), and it."""
    n = len(u)
    top = min(max_degree, n - 2 - MIN_POINTS_PER_COEF)
    if top < 1:
        return max(1, min(n - 1, 1)), math.nan
    best = (1, math.inf)
    for degree in range(1, top + 1):
        errs = []
        for i in range(n):
            mask = np.arange(n) != i
            coef = _polyfit(u[mask], p[mask], s[mask], degree)
            errs.append(float(np.polynomial.polynomial.polyval(u[i], coef)) - p[i])
        rms = math.sqrt(float(np.mean(np.square(errs))))
        if rms < best[1]:
            best = (degree, rms)
    return best


def _check_monotone(points: list[DepthPoint]) -> None:
    pts = sorted(points, key=lambda p: p.at)
    counts = [p.counts for p in pts]
    v = [p.v_mm for p in pts]
    steps = [b - a for a, b in itertools.pairwise(v)]
    monotone = all(d > 0 for d in steps) or all(d < 0 for d in steps)
    if len(set(counts)) != len(counts) or not monotone:
        raise CalibrationError(
            "the sharpest settings are not monotone in depth "
            f"(counts {counts}, v {[round(x, 4) for x in v]}); use depths further apart"
        )


def _fit_anchored(points: list[DepthPoint], f: float, span: tuple[float, float]) -> ModelFit:
    """The focus model through the points and the infinity anchor (the far end of the focus
    range focuses at infinity: the camera's datasheet); the fit's per-depth figures are the
    points' (the anchor's dropped)."""
    counts, z, sigma = _anchored_inputs(points, span)
    fit = fit_focus_model(counts, z, sigma, f, span)
    return dataclasses.replace(
        fit,
        used=fit.used[:-1],
        residual_v_um=fit.residual_v_um[:-1],
        residual_depth_mm=fit.residual_depth_mm[:-1],
    )


def _anchored_inputs(
    points: list[DepthPoint], span: tuple[float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Counts, depth and σ (counts) of the points and of the infinity anchor (last)."""
    counts = np.array([*(p.at for p in points), span[0]])
    sigma = np.array([p.sigma_counts for p in points])
    # a point without a σ (a rig that gave none) weighs as the median of the others
    fallback = float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else 1.0
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, fallback)
    sigma = np.r_[sigma, float(np.median(sigma))]
    z = np.array([*(p.z_m for p in points), math.inf])
    return counts, z, sigma


def _by_depth(points: list[DepthPoint]) -> list[list[DepthPoint]]:
    """The points grouped by depth (repeated sweeps of one depth together), in depth order."""
    groups: dict[float, list[DepthPoint]] = {}
    for p in points:
        groups.setdefault(p.z_m, []).append(p)
    return [groups[z] for z in sorted(groups)]


def _refit_in_v(point: DepthPoint, model: Any, half_width_mm: float) -> DepthPoint:
    """``point``'s vertex refitted with the sweep's settings mapped to v through ``model``, on
    a window of ``half_width_mm`` either side (the estimator's burst bracket)."""
    if len(point.sweep) < 3:
        return point
    c, g, s = (np.array(col) for col in zip(*point.sweep, strict=True))
    v = model.v_mm(c)
    order = np.argsort(v)
    found = fit_vertex(v[order], g[order], s[order], half_width_mm)
    if found is None:
        return point
    lo, hi = float(c.min()), float(c.max())
    at = model.counts_for_v(found.x, lo, hi)
    slope = abs(float(np.gradient(v, c)[int(np.argmin(np.abs(c - at)))]))
    sigma = found.sigma / slope if slope > 0 else point.sigma_counts
    return dataclasses.replace(point, counts=round(at), counts_exact=at, sigma_counts=sigma)


def _tabulate(
    model: FocusModel, measured: tuple[float, float], focus_range: tuple[float, float]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """The model every TABLE_STEP_COUNTS over the whole focus range: the estimator's brackets
    reach ~90 µm of v beyond the target (past 20 m towards infinity at 10 m), and a table that
    stops at the last calibrated depth shifts them off-centre (paper-circle: 8 -> 157 mm ss RMS
    with the true table cut to 1.2-20 m). Beyond the measured depths the model extrapolates
    while it stays monotone and in front of infinity (P > 0)."""
    lo, hi = sorted(focus_range)
    grid = np.unique(np.r_[np.arange(math.ceil(lo), hi, TABLE_STEP_COUNTS), math.floor(hi)])
    power = model.power_dpt(grid)
    v = model.v_mm(grid)
    inside = (grid >= measured[0]) & (grid <= measured[1])
    rising = np.diff(v) > 0
    first, last = int(np.flatnonzero(inside)[0]), int(np.flatnonzero(inside)[-1])
    if not (rising[first:last].all() or not rising[first:last].any()):
        raise CalibrationError(
            "the fitted focus model is not monotone over the calibrated range; check the "
            "depths printed with large residuals and re-measure them"
        )
    step_up = bool(rising[first]) if last > first else True
    while first > 0 and bool(rising[first - 1]) == step_up and power[first - 1] > 0:
        first -= 1
    while last < len(grid) - 1 and bool(rising[last]) == step_up and power[last + 1] > 0:
        last += 1
    return grid[first : last + 1].astype(np.int64), v[first : last + 1]


def _with_f_number(lens: Lens, f_number: float | None, zoom_counts: int | None) -> Lens:
    return dataclasses.replace(lens, f_number=f_number, zoom_counts=zoom_counts)
