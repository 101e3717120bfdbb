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
``P(u)`` is a polynomial in the normalised counts ``u`` plus, where it predicts better, a
smoothing spline of its residuals (a cam ripple); the degree and the spline's smoothing are
chosen by cross-validation that leaves out one depth at a time (all the points of its sweeps),
outliers beyond :data:`OUTLIER_SIGMA` robust σ are dropped, and the residuals are reported in v
(µm) and in depth (mm). ``v(counts) = 1 / (1/f − P)`` is then tabulated densely for the lens file.

Lens table (:func:`fit_table`). A first model goes through the sweeps' least-squares vertices
(in counts) and the infinity anchor at the far end of the focus range. Then, pass after pass,
each sweep is read through the latest model's polynomial as the v axis where the estimator's
closed loop settles on it (:func:`dffd.calibrate_vertex.closed_loop_vertex`: the burst bracket
whose two ends cost the same), and the model is refitted through the two ends of each settled
bracket, at v − h and v + h of the depth: on that table the loop settles at v and reads the
calibrated depth whatever the lens's point-spread function (docs/estimation.md §16). The table
is the model every :data:`TABLE_STEP_COUNTS` over the focus range where it stays monotone. With
fewer than :data:`MIN_MODEL_DEPTHS` depths the table is the points themselves
(:func:`lens_from_points`).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, make_smoothing_spline

from dffd.calibrate_vertex import closed_loop_vertex
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
SPLINE_MIN_POINTS = 6  # a residual spline needs this many depths (scipy: 5 points)
MAX_BASE_DEGREE = 3  # the polynomial under the spline: at most cubic (the spline does the rest)
# Smoothing of the residual spline (weights normalised to a mean of one, u in [0, 1]): from
# nearly interpolating to nearly straight, a decade apart; the one that predicts left-out depths
# best is kept (or no spline). Generalised cross-validation on single points chose no smoothing
# (it interpolated the scatter: two points of one sweep vouch for each other).
SPLINE_LAMBDAS = tuple(10.0**k for k in range(-9, 1))
KNOT_DECIMALS = 6  # settings closer than 1e-6 of the focus range share a spline knot
TABLE_STEP_COUNTS = 256  # spacing of the written table's rows (PCHIP of a smooth model: exact)
# Half-width of the vertex window of the refit in v, in px of blur radius: the estimator's own
# burst bracket (PlanConfig.outer_blur_px, 3 px), where a measure's lean on a lens is the one its
# bursts fit. Chosen on the reference optics (paper-circle seed 1, 60 s, peak_gradient): 1 px ->
# table 14 mm rms, bench 28 mm; 3 px -> 3.6 mm, 8.8 mm (true table: 8.0 mm). On the aberrated
# optics the bench is the same with 1 or 3 px (docs/estimation.md §10).
VERTEX_WINDOW_BLUR_PX = PlanConfig().outer_blur_px
# Refit passes through the latest model's polynomial (the bracket ends move < 0.1 µm after ~4).
# The axis is the polynomial, not the residual spline: through the spline the passes feed each
# reading's scatter back into the axis (reference optics seed 1: table 2.3 -> 11.1 mm rms).
REFIT_PASSES = 8
SETTLED_SIGMA = 0.05  # the passes stop when no bracket end moves by more than this × its σ
# The fit missing its own bracket ends by more than this many of their σ (rms) means the axis
# misses the focus curve: the passes go on through the whole model (polynomial and spline). The
# same limit as a depth the others predict badly (calibrate_check.REPEAT_SIGMA).
AXIS_MISFIT_SIGMA = 3.0
MIN_MODEL_DEPTHS = 4  # fewer depths: the table is the measured points themselves
# Repeated sweeps of one depth (combine_sweeps): with three or more, a sweep whose vertex is more
# than this many of its σ from the others' median is dropped (a disturbed sweep: the target
# knocked, a lighting flicker); the combined σ is scaled up by the sweeps' own disagreement.
SWEEP_OUTLIER_SIGMA = 4.0
# fit_table(levels=True): the model is fitted to each settled bracket's level — the table's
# mean v over its two ends is the depth's v — instead of to the two ends at v ∓ h, whose width
# on the axis read is the axis's own (docs/estimation.md §18, §20). Not the default: measured
# worse on held-out sweeps of the aberrated optics (§20).
LEVEL_NEWTON_STEPS = 4  # the mean-power correction converges quadratically from P(v)


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
    # how the vertex was read: "least squares" (fit_vertex), "closed loop" (the burst bracket's
    # fixed point) or "closed loop, pinned" (the bracket shifted at an end of the focus range)
    rule: str = "least squares"
    # a bracket end stands for v ∓ h of the sweep's depth; the depth the target was placed at
    target_m: float = math.nan  # NaN: z_m itself
    # a bracket's level (rule "bracket level"): the counts of the settled bracket's other end;
    # the table's mean v at ``at`` and ``pair_at`` is the depth's v (``z_m``: the depth of the
    # mean focus power that gives it). NaN: a point, the table's v at ``at`` is ``v_mm``.
    pair_at: float = math.nan

    @property
    def placed_m(self) -> float:
        """The depth the target was placed at for this sweep."""
        return self.z_m if math.isnan(self.target_m) else self.target_m

    @property
    def at(self) -> float:
        """The sharpest counts, unrounded."""
        return self.counts if math.isnan(self.counts_exact) else self.counts_exact

    @property
    def other(self) -> float:
        """The bracket's other end for a level, else ``at`` (the constraint's second setting)."""
        return self.at if math.isnan(self.pair_at) else self.pair_at


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
    spline_lam: float = math.nan  # its smoothing (chosen by cross-validation; NaN: no spline)

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
    # the points the model was fitted to: the settled brackets' ends (two a depth), or the
    # depth points themselves (empty: ``points``)
    fit_points: tuple[DepthPoint, ...] = ()
    # the refit passes' v axis: "polynomial" (the model's polynomial), or "whole model"
    # (polynomial and spline) when the polynomial axis missed its own bracket ends by more than
    # AXIS_MISFIT_SIGMA (a cam ripple); and that misfit (rms, in the ends' σ; NaN: no refit)
    axis: str = "polynomial"
    axis_misfit_sigma: float = math.nan

    @property
    def model_points(self) -> tuple[DepthPoint, ...]:
        """The points the focus model went through (``fit``'s per-point figures are theirs)."""
        return self.fit_points or self.points

    def residual_lines(self) -> list[str]:
        """One line per depth: where the closed loop reads its sweep (counts, v), how, and the
        model's residual at the points it was fitted to there (for the CLI)."""
        lines = []
        fitted = self.model_points
        for p in self.points:
            line = f"z = {p.z_m:6.2f} m  read at counts {p.at:9.1f}"
            if not math.isnan(p.sigma_counts):
                line += f" ± {p.sigma_counts:5.1f}"
            line += f"  v = {p.v_mm:.6f} mm ({p.rule})"
            if self.fit is not None:
                mine = [i for i, q in enumerate(fitted) if q.placed_m == p.placed_m]
                if not mine:
                    line += "  not fitted (the bracket meets the end of the focus range)"
                for i in mine:
                    q = fitted[i]
                    where = (
                        ""
                        if q is p or q.rule != "bracket end"
                        else (f" at v {q.v_mm - p.v_mm:+.4f} mm")
                    )
                    line += f"; residual{where} {self.fit.residual_v_um[i]:+6.3f} µm of v" + (
                        "" if self.fit.used[i] else " REJECTED (outlier: re-measure)"
                    )
            lines.append(line)
        if self.fit is not None:
            m = self.fit
            spline = (
                ""
                if m.model.spline is None
                else (f" + smoothing spline (λ = {m.model.spline_lam:.0e})")
            )
            lines.append(
                f"focus model: P(counts) polynomial of degree {m.model.degree}{spline} "
                f"(cross-validated), {sum(m.used)} of {len(m.used)} points; residual rms "
                f"{m.rms_v_um:.3f} µm of v, {m.rms_depth_mm:.1f} mm of depth; leave-one-depth-out "
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
    *,
    groups: npt.ArrayLike | None = None,
    structure: tuple[int, float] | None = None,
    counts_b: npt.ArrayLike | None = None,
) -> ModelFit:
    """P(counts) through the depths' points; structure by cross-validation, outliers dropped.

    ``counts_span`` normalises the counts (the focus range: far end, near end); ``groups``: the
    depth each point's sweep was taken at (cross-validation leaves a depth out; NaN: a point
    always kept; None: each point its own depth); ``structure``: (degree, spline smoothing)
    imposed instead of chosen; ``counts_b``: per point a second setting — the model's mean power
    at ``counts`` and ``counts_b`` is fitted to 1/z (a bracket's level; None or equal: a point).
    """
    labels = (
        np.arange(len(z_m), dtype=np.float64)
        if groups is None
        else np.asarray(groups, dtype=np.float64)
    )
    power = 1.0 / np.asarray(z_m, dtype=np.float64)
    lo, hi = counts_span
    ca = np.asarray(counts, dtype=np.float64)
    cb = ca if counts_b is None else np.asarray(counts_b, dtype=np.float64)
    u = np.stack([(ca - lo) / (hi - lo), (cb - lo) / (hi - lo)], axis=1)  # n × 2 settings
    sigma_p = _power_sigma(u, power, np.asarray(sigma_counts, dtype=np.float64), hi - lo)
    used = np.ones(len(u), dtype=bool)
    max_drop = int(MAX_OUTLIER_FRACTION * len(u))
    while True:
        model, loo = _fit_model(
            u[used], power[used], sigma_p[used], (lo, hi), focal_length_mm,
            groups=labels[used], structure=structure,
        )  # fmt: skip
        p_model = 0.5 * (model.power_dpt(ca) + model.power_dpt(cb))
        resid = (power - p_model) / sigma_p
        r_used = resid[used]
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(r_used - np.median(r_used)))), 1.0)
        worst = int(np.argmax(np.where(used, np.abs(resid), -np.inf)))
        if abs(resid[worst]) <= OUTLIER_SIGMA * scale or (~used).sum() >= max_drop:
            break
        used[worst] = False
    v_meas = 1.0 / (1.0 / focal_length_mm - power / MM_PER_M)
    v_model = 1.0 / (1.0 / focal_length_mm - p_model / MM_PER_M)
    with np.errstate(divide="ignore", invalid="ignore"):  # a depth at infinity: P = 0
        z_model = 1.0 / p_model
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
    *,
    levels: bool = False,
) -> TableFit:
    """The calibrated lens: a smooth focus model through the depth points (vertices refitted in
    v through it, on ± ``window_blur_px`` of blur), tabulated densely; with fewer than
    MIN_MODEL_DEPTHS depths, the points themselves. ``levels``: fit each settled bracket's
    level (the mean of the table over its two ends) instead of its two ends, through the whole
    model as the axis (docs/estimation.md §20)."""
    f, pitch = rig.focal_length_mm, rig.pixel_pitch_mm
    groups = _by_depth(points)
    points = [combine_sweeps(g) for g in groups]
    if len(points) < MIN_MODEL_DEPTHS:
        lens = lens_from_points(name, f, pitch, points)
        return TableFit(tuple(points), None, _with_f_number(lens, f_number, rig.zoom_counts))
    _check_monotone(points)
    span = (float(rig.focus_range[0]), float(rig.focus_range[1]))
    fit_points = points
    # The model is anchored at P = 0 at the far end of the focus range (focus at infinity, the
    # VISCA camera's datasheet, docs/design.md §6): the estimator's brackets at 10 m reach far
    # past the last calibrated depth, and there an unanchored model's cam ripple is free
    # (aberrated optics, seed 1: a true 100 m read as 44 m; bench 771 -> 483 mm ss RMS on 60 s,
    # true table 481 mm; reference unchanged).
    model = _fit_anchored(points, f, span)
    # Refit passes: each sweep read where the estimator's closed loop settles on it, through
    # the latest model as the v axis (the estimator plans and fits its bursts in the table's v).
    # A sweep read there gives the two ends of its settled bracket, counts a and b of equal
    # cost: the table must map them to v − h and v + h of the depth (then the closed loop, on
    # this table, settles at v and reads the depth). The bracket ends of the nearer depths
    # reach to ~f + 10 µm (a 10 m target), where no target can be calibrated: the table near
    # infinity is measured where the estimator uses it (docs/estimation.md §16). Depths whose
    # bracket meets the end of the focus range (beyond ~11 m) give no pair and are not fitted.
    n_f = f_number if f_number is not None else PlanConfig().default_f_number
    per_px = pitch * n_f * 2.0 / f  # mm of v per px of blur radius, per mm of v (plan_burst)
    model, refit, fit_points = _settle(
        groups, model, points, span, per_px * window_blur_px, levels=levels
    )
    # A focus curve the polynomial cannot follow (a cam ripple) leaves the bracket ends of
    # neighbouring depths inconsistent through the polynomial axis: the fit then misses its own
    # points by many of their σ. Only then the passes go on with the whole model (polynomial and
    # spline) as the axis; through the spline a model that needs none feeds the readings'
    # scatter back (reference optics: misfit 0.4-0.8 σ rms, polynomial axis kept).
    # Levels fix no width: their pairs must be read through the table itself (its own width),
    # or the estimator's brackets on it are not the pairs calibrated (a polynomial axis on a
    # rippled cam: widths 20 % off; held-out aberrated sweeps read 86-94 mm rms, §20).
    misfit = _misfit_sigma(model, fit_points)
    axis = "polynomial"
    if misfit > AXIS_MISFIT_SIGMA or levels:
        axis = "whole model"
        model, refit, fit_points = _settle(
            groups, model, points, span, per_px * window_blur_px, spline_axis=True,
            levels=levels,
        )  # fmt: skip
    ats = [p.at for p in (*refit, *fit_points)]
    grid, v = _tabulate(model.model, (min(ats), max(ats)), span)
    lens = Lens(
        name, f, pitch, tuple(int(c) for c in grid), tuple(float(x) for x in v),
        f_number=f_number, zoom_counts=rig.zoom_counts,
        table_sigma_v_mm=model.table_sigma_v_um / 1000.0,
    )  # fmt: skip
    return TableFit(tuple(refit), model, lens, tuple(fit_points), axis, misfit)


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


def model_v_mm(model: FocusModel, point: DepthPoint) -> float:
    """The model's v where ``point`` constrains it: at its counts, or a level's mean over its
    bracket's two ends (compare with ``point.v_mm``)."""
    return float(np.mean(model.v_mm([point.at, point.other])))


def model_with_structure(
    points: list[DepthPoint], f: float, span: tuple[float, float], like: FocusModel
) -> FocusModel:
    """The anchored focus model of ``like``'s structure (degree, spline or not) through
    ``points``, without choosing it again: for resampling the table's uncertainty."""
    counts, counts_b, z, sigma_counts, _ = _anchored_inputs(points, span)
    lo, hi = span
    u = np.stack([(counts - lo) / (hi - lo), (counts_b - lo) / (hi - lo)], axis=1)
    power = 1.0 / z
    sigma_p = _power_sigma(u, power, sigma_counts, hi - lo)
    return _build_model(u, power, sigma_p, span, f, degree=like.degree, lam=like.spline_lam)


# -- private helpers --------------------------------------------------------------------------
def _build_model(
    u: FloatArray,
    p: FloatArray,
    s: FloatArray,
    span: tuple[float, float],
    f: float,
    *,
    degree: int,
    lam: float,
) -> FocusModel:
    """The weighted polynomial of ``degree`` through (u, p), plus a residual smoothing spline of
    smoothing ``lam`` (NaN: none)."""
    base = FocusModel(tuple(float(c) for c in _polyfit(u, p, s, degree)), *span, f)
    return base if math.isnan(lam) else _with_spline(base, u, p, s, lam)


def _power_sigma(
    u: FloatArray, power: FloatArray, sigma_counts: FloatArray, width: float
) -> FloatArray:
    """σ of P from the vertex's σ in counts through the local slope of a first straight fit
    (``u``: n × 2 settings, a point's two equal)."""
    slope = abs(np.polyfit(u.mean(axis=1), power, 1)[0])
    return np.asarray(np.maximum(slope * np.asarray(sigma_counts) / width, 1e-9), dtype=np.float64)


def _fit_model(
    u: FloatArray,
    p: FloatArray,
    s: FloatArray,
    span: tuple[float, float],
    f: float,
    *,
    groups: FloatArray,
    structure: tuple[int, float] | None = None,
) -> tuple[FocusModel, float]:
    """Polynomial (degree by cross-validation, at most MAX_BASE_DEGREE), with a residual
    smoothing spline whose smoothing is chosen by cross-validation among SPLINE_LAMBDAS (or
    none); and the cross-validated error (dioptres rms). Cross-validation leaves out one depth
    at a time — every point of that depth's sweeps (``groups``: the depth; NaN: always kept,
    the infinity anchor) — so that two points of one sweep cannot vouch for each other."""
    if structure is None:
        degree, _ = _choose_degree(u, p, s, MAX_BASE_DEGREE, groups)
        lambdas: tuple[float, ...] = (math.nan, *SPLINE_LAMBDAS)
    else:
        degree, lambdas = structure[0], (structure[1],)

    def build(mask: BoolArray, lam: float) -> FocusModel:
        return _build_model(u[mask], p[mask], s[mask], span, f, degree=degree, lam=lam)

    n_depths = len(np.unique(groups[np.isfinite(groups)]))
    best: tuple[float, float] = (math.inf, math.nan)
    for lam in lambdas:
        if not math.isnan(lam) and n_depths < SPLINE_MIN_POINTS:
            break
        rms = _cross_validated(u, p, groups, functools.partial(build, lam=lam), span)
        if rms < best[0]:
            best = (rms, lam)
    return build(np.ones(len(u), dtype=bool), best[1]), best[0]


def _cross_validated(
    u: FloatArray,
    p: FloatArray,
    groups: FloatArray,
    build: Callable[[BoolArray], FocusModel],
    span: tuple[float, float],
) -> float:
    """RMS error (dioptres) of each depth's points predicted by the model built without them."""
    errs: list[float] = []
    for g in np.unique(groups[np.isfinite(groups)]):
        out = groups == g
        try:
            other = build(~out)
        except ValueError:  # too few points left for the structure
            return math.inf
        pred = _mean_power(other, u[out], span)
        errs.extend(float(x) for x in pred - p[out])
    return math.sqrt(float(np.mean(np.square(errs)))) if errs else math.inf


def _with_spline(
    model: FocusModel, u: FloatArray, p: FloatArray, s: FloatArray, lam: float
) -> FocusModel:
    """``model`` plus a smoothing spline of its residuals with smoothing ``lam`` (weights
    normalised to a mean of one, u in [0, 1]): the cam's ripples the polynomial misses. Each
    row of ``u`` holds a constraint's two settings: the spline's mean there is fitted (a
    point's two are equal)."""
    if len(u) < SPLINE_MIN_POINTS:
        return model
    span = (model.counts_lo, model.counts_hi)
    r = p - _mean_power(model, u, span)
    w = 1.0 / s**2
    w = w / float(np.mean(w))
    if np.array_equal(u[:, 0], u[:, 1]):  # points only: scipy's smoothing spline
        order = np.argsort(u[:, 0])
        uo = u[order, 0]
        if np.any(np.diff(uo) <= 0):
            raise ValueError("a spline needs distinct settings")
        spline = make_smoothing_spline(uo, r[order], w=w[order], lam=lam)
    else:
        spline = _mean_smoothing_spline(u, r, w, lam)
    return FocusModel(
        model.coef, model.counts_lo, model.counts_hi, model.focal_length_mm, spline,
        (float(u.min()), float(u.max())), lam,
    )  # fmt: skip


def _mean_smoothing_spline(u: FloatArray, r: FloatArray, w: FloatArray, lam: float) -> BSpline:
    """The cubic spline s minimising Σ w (½(s(u₀) + s(u₁)) − r)² + lam ∫ s''² over the rows
    (u₀, u₁) of ``u``: a smoothing spline fitted to means of two values (a bracket's level)
    instead of to values. The minimiser over all functions is a natural cubic spline with knots
    at every setting (as for points), so the B-spline basis on those knots is exact; for points
    (u₀ = u₁) this is scipy's ``make_smoothing_spline``."""
    knots = np.unique(np.round(u.ravel(), KNOT_DECIMALS))
    if len(knots) < 4:
        raise ValueError("a spline needs at least four distinct settings")
    t = np.r_[[knots[0]] * 3, knots, [knots[-1]] * 3]
    n_basis = len(t) - 4
    clipped = np.clip(u, knots[0], knots[-1])
    design = 0.5 * (
        BSpline.design_matrix(clipped[:, 0], t, 3).toarray()
        + BSpline.design_matrix(clipped[:, 1], t, 3).toarray()
    )
    # ∫ B_i'' B_j'': B'' is linear on each knot interval, so two Gauss points are exact
    a, b = knots[:-1], knots[1:]
    gauss = 0.5 / math.sqrt(3.0)
    nodes = np.r_[0.5 * (a + b) - gauss * (b - a), 0.5 * (a + b) + gauss * (b - a)]
    weights = np.r_[0.5 * (b - a), 0.5 * (b - a)]
    second = np.stack(
        [BSpline(t, np.eye(n_basis)[k], 3).derivative(2)(nodes) for k in range(n_basis)], axis=1
    )
    penalty = second.T @ (second * weights[:, None])
    normal = design.T @ (design * w[:, None]) + lam * penalty
    coef = np.linalg.lstsq(normal, design.T @ (w * r), rcond=None)[0]
    return BSpline(t, coef, 3)


def _mean_power(model: FocusModel, u: FloatArray, span: tuple[float, float]) -> FloatArray:
    """The model's mean focus power over each row's two settings (normalised counts)."""
    counts = u * (span[1] - span[0]) + span[0]
    return np.asarray(
        0.5 * (model.power_dpt(counts[:, 0]) + model.power_dpt(counts[:, 1])), dtype=np.float64
    )


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
    """Weighted least-squares polynomial (lowest degree first) whose mean over each row's two
    settings ``u`` fits ``p``."""
    vander = 0.5 * (
        np.vander(u[:, 0], degree + 1, increasing=True)
        + np.vander(u[:, 1], degree + 1, increasing=True)
    )
    design = vander / s[:, None]
    coef, *_ = np.linalg.lstsq(design, p / s, rcond=None)
    return np.asarray(coef, dtype=np.float64)


def _choose_degree(
    u: FloatArray, p: FloatArray, s: FloatArray, max_degree: int, groups: FloatArray
) -> tuple[int, float]:
    """The degree with the smallest cross-validated error (dioptres RMS, one depth left out at
    a time), and it."""
    n = len(np.unique(groups[np.isfinite(groups)])) + int((~np.isfinite(groups)).sum())
    top = min(max_degree, n - 2 - MIN_POINTS_PER_COEF)
    if top < 1:
        return max(1, min(n - 1, 1)), math.nan
    best = (1, math.inf)
    span = (0.0, 1.0)
    for degree in range(1, top + 1):

        def build(mask: BoolArray, degree: int = degree) -> FocusModel:
            return FocusModel(
                tuple(float(c) for c in _polyfit(u[mask], p[mask], s[mask], degree)), *span, 1.0
            )

        rms = _cross_validated(u, p, groups, build, span)
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


def _fit_anchored(
    points: list[DepthPoint],
    f: float,
    span: tuple[float, float],
    structure: tuple[int, float] | None = None,
) -> ModelFit:
    """The focus model through the points and the infinity anchor (the far end of the focus
    range focuses at infinity: the camera's datasheet); the fit's per-depth figures are the
    points' (the anchor's dropped)."""
    counts, counts_b, z, sigma, groups = _anchored_inputs(points, span)
    fit = fit_focus_model(
        counts, z, sigma, f, span, groups=groups, structure=structure, counts_b=counts_b
    )
    # in depth: the error a target at the sweep's own depth would see (a bracket end stands
    # for a v, not for a depth a target was at)
    placed = np.array([p.placed_m for p in points]) * MM_PER_M
    dz_dv = (placed / (placed - f)) ** 2  # |dz/dv| of the thin lens at the placed depth
    depth_mm = np.asarray(fit.residual_v_um[:-1]) * 1e-3 * dz_dv
    return dataclasses.replace(
        fit,
        used=fit.used[:-1],
        residual_v_um=fit.residual_v_um[:-1],
        residual_depth_mm=tuple(float(x) for x in depth_mm),
    )


def _anchored_inputs(
    points: list[DepthPoint], span: tuple[float, float]
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Counts, the second counts of a level (:attr:`DepthPoint.other`), depth, σ (counts) and
    the placed depth (NaN: the anchor) of the points and of the infinity anchor (last)."""
    counts = np.array([*(p.at for p in points), span[0]])
    counts_b = np.array([*(p.other for p in points), span[0]])
    sigma = np.array([p.sigma_counts for p in points])
    # a point without a σ (a rig that gave none) weighs as the median of the others
    fallback = float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else 1.0
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, fallback)
    sigma = np.r_[sigma, float(np.median(sigma))]
    z = np.array([*(p.z_m for p in points), math.inf])
    groups = np.array([*(p.placed_m for p in points), math.nan])
    return counts, counts_b, z, sigma, groups


def _by_depth(points: list[DepthPoint]) -> list[list[DepthPoint]]:
    """The points grouped by depth (repeated sweeps of one depth together), in depth order."""
    groups: dict[float, list[DepthPoint]] = {}
    for p in points:
        groups.setdefault(p.z_m, []).append(p)
    return [groups[z] for z in sorted(groups)]


def _closed_loop_read(
    point: DepthPoint,
    model: Any,
    half_width_mm: float,
    span: tuple[float, float],
    *,
    levels: bool = False,
) -> tuple[DepthPoint, ...]:
    """``point``'s sweep read through ``model`` as the v axis: where the estimator's closed
    loop settles with a bracket of ± ``half_width_mm`` (:func:`closed_loop_vertex`) — the
    bracket's two ends (points at v ∓ h of the depth) and its centre (the depth); or, where the
    bracket meets the end of the focus range ``span`` or the sweep does not reach it, only the
    depth point, read at the pinned bracket or at the least-squares vertex of the window. With
    ``levels`` the two ends come as one level point (:attr:`DepthPoint.pair_at`) and the
    centre."""
    if len(point.sweep) < 3:
        return (point,)
    c, g, s = (np.array(col) for col in zip(*point.sweep, strict=True))
    v = model.v_mm(c)
    order = np.argsort(v)
    found = fit_vertex(v[order], g[order], s[order], half_width_mm)
    if found is None:
        return (point,)
    lo, hi = float(c.min()), float(c.max())

    def at_v(x: float, sigma_v: float, rule: str, offset_mm: float = 0.0) -> DepthPoint:
        """The point at ``x`` (the model's v) standing for the depth's v + ``offset_mm``."""
        at = model.counts_for_v(x, lo, hi)
        slope = abs(float(np.gradient(v, c)[int(np.argmin(np.abs(c - at)))]))
        sigma = sigma_v / slope if slope > 0 else point.sigma_counts
        v_mm = point.v_mm + offset_mm
        f = model.focal_length_mm
        # the depth in focus at v_mm (negative beyond infinity: P = 1/z < 0)
        z_m = point.z_m if offset_mm == 0 else f * v_mm / (v_mm - f) / MM_PER_M
        return dataclasses.replace(
            point, z_m=z_m, v_mm=v_mm, counts=round(at), counts_exact=at, sigma_counts=sigma,
            rule=rule, target_m=point.placed_m,
        )  # fmt: skip

    ends = (float(model.v_mm(span[0])), float(model.v_mm(span[1])))
    loop = closed_loop_vertex(v, g, s, half_width_mm, start=found.x, ends=ends)
    if loop is None:
        return (at_v(found.x, found.sigma, "least squares"),)
    if loop.pinned:
        return (at_v(loop.x, loop.sigma, "closed loop, pinned"),)
    h = half_width_mm
    if levels:
        a = at_v(loop.x - h, loop.sigma, "bracket end", -h)
        b = at_v(loop.x + h, loop.sigma, "bracket end", h)
        level = dataclasses.replace(
            at_v(loop.x, loop.sigma, "bracket level"),
            counts_exact=a.at,
            pair_at=b.at,
            z_m=_level_depth_m(point.v_mm, model.power_dpt([a.at, b.at]), model.focal_length_mm),
        )
        return (level, at_v(loop.x, loop.sigma, "closed loop"))
    return (
        at_v(loop.x - h, loop.sigma, "bracket end", -h),
        at_v(loop.x + h, loop.sigma, "bracket end", h),
        at_v(loop.x, loop.sigma, "closed loop"),
    )


def _settle(
    groups: list[list[DepthPoint]],
    model: ModelFit,
    points: list[DepthPoint],
    span: tuple[float, float],
    h_per_v: float,
    *,
    spline_axis: bool = False,
    levels: bool = False,
) -> tuple[ModelFit, list[DepthPoint], list[DepthPoint]]:
    """Refit passes until the bracket ends stop moving: each sweep read through the model (its
    polynomial, or the whole model with ``spline_axis``), the model refitted through the ends;
    the model, the depth points (where each depth is read) and the points it was fitted to."""
    f = model.model.focal_length_mm
    refit, fit_points = points, points
    structure: tuple[int, float] | None = None
    for k in range(REFIT_PASSES):
        mapping = model.model if spline_axis else dataclasses.replace(model.model, spline=None)
        ends: list[DepthPoint] = []
        centres: list[DepthPoint] = []
        for g in groups:
            reads = [
                _closed_loop_read(p, mapping, h_per_v * p.v_mm, span, levels=levels) for p in g
            ]
            level_reads = [r for r in reads if len(r) == 2]
            pairs = [r for r in reads if len(r) == 3]
            if level_reads:
                ends.append(_combine_levels([r[0] for r in level_reads]))
                centres.append(combine_sweeps([r[1] for r in level_reads]))
            elif pairs:
                ends += [
                    combine_sweeps([r[0] for r in pairs]),
                    combine_sweeps([r[1] for r in pairs]),
                ]
                centres.append(combine_sweeps([r[2] for r in pairs]))
            else:
                centres.append(combine_sweeps([r[-1] for r in reads]))
        if len({p.placed_m for p in ends}) < MIN_MODEL_DEPTHS:
            break
        settled = len(ends) == len(fit_points) and all(
            max(abs(a.at - b.at), abs(a.other - b.other)) < SETTLED_SIGMA * a.sigma_counts
            for a, b in zip(ends, fit_points, strict=True)
        )
        refit, fit_points = centres, ends
        # the model's structure (degree, smoothing) is chosen on the first and the last pass
        last = settled or k == REFIT_PASSES - 1
        model = _fit_anchored(ends, f, span, None if last else structure)
        structure = (model.model.degree, model.model.spline_lam)
        if settled:
            break
    return model, refit, fit_points


def _level_depth_m(v_mm: float, power_ab: FloatArray, f: float) -> float:
    """The depth (m) whose focus power P̄ is a bracket level's mean power: the table's mean v
    over two powers P̄ ∓ d (d their half-difference on the axis read) is ``v_mm`` exactly — the
    mean of v is not v of the mean power (v is convex in P: ~0.3 µm at h = 90 µm)."""
    d = 0.5 * float(power_ab[1] - power_ab[0])
    power = (1.0 / f - 1.0 / v_mm) * MM_PER_M  # dioptres: P of v_mm itself
    for _ in range(LEVEL_NEWTON_STEPS):
        va, vb = (1.0 / (1.0 / f - q / MM_PER_M) for q in (power - d, power + d))
        power -= (0.5 * (va + vb) - v_mm) / (0.5 * (va * va + vb * vb) / MM_PER_M)
    return 1.0 / power if power != 0 else math.inf


def _combine_levels(levels: list[DepthPoint]) -> DepthPoint:
    """One level from repeated sweeps of one depth: each end combined as a point
    (:func:`combine_sweeps`), the mean power kept from the sweep nearest the combined ends."""
    if len(levels) == 1:
        return levels[0]
    a = combine_sweeps(levels)
    b = combine_sweeps([dataclasses.replace(p, counts_exact=p.pair_at) for p in levels])
    return dataclasses.replace(a, pair_at=b.at)


def _misfit_sigma(model: ModelFit, points: list[DepthPoint]) -> float:
    """RMS of the model's residuals at ``points`` in units of their own σ (the points used)."""
    if len(points) != len(model.residual_v_um):
        return 0.0
    at = np.array([p.at for p in points])
    slope = np.abs(model.model.v_mm(at + 0.5) - model.model.v_mm(at - 0.5))  # mm per count
    sigma_um = np.array([p.sigma_counts for p in points]) * slope * 1e3
    r = np.asarray(model.residual_v_um) / sigma_um
    used = np.asarray(model.used) & np.isfinite(r)
    return float(np.sqrt(np.mean(r[used] ** 2))) if used.any() else 0.0


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
