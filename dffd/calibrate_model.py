"""The smooth focus model of ``dffd calibrate``: focus power P(counts) through the depth
points and the infinity anchor.

Pure numerics (no rig, no I/O). The thin lens turns each depth z into a focus power ``P = 1/z``
(dioptres); the lens's focus cam makes ``P`` a smooth monotone function of counts. ``P(u)`` is a
polynomial in the normalised counts ``u`` plus, where it predicts better, a smoothing spline of
its residuals (a cam ripple); the degree and the spline's smoothing are chosen by
cross-validation that leaves out one depth at a time (all the points of its sweeps), outliers
beyond :data:`OUTLIER_SIGMA` robust σ are dropped, and the residuals are reported in v (µm) and
in depth (mm) (:func:`fit_focus_model`). Through depth points the model is anchored at ``P = 0``
at the far end of the focus range, where the camera focuses at infinity
(:func:`fit_anchored`); :func:`model_with_structure` refits it with its structure kept (the
table's bootstrap, :mod:`dffd.calibrate_check`). ``v(counts) = 1 / (1/f − P)`` is tabulated
densely for the lens file by :func:`dffd.calibrate_fit.fit_table`.

Split from :mod:`dffd.calibrate_fit` (the lens table fitted through this model).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, make_smoothing_spline

from dffd.calibrate_parabola import MAD_TO_SIGMA, OUTLIER_SIGMA
from dffd.calibrate_types import DepthPoint
from dffd.core.lens import MM_PER_M

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

# A depth beyond OUTLIER_SIGMA robust σ (MAD_TO_SIGMA per median absolute deviation) is dropped:
# the rule of a sweep's vertex (calibrate_parabola).
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


def fit_anchored(
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
