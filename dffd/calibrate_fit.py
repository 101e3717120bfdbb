"""The fits of ``dffd calibrate``: the sharpest setting of one sweep, the smooth focus model.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, make_smoothing_spline

from dffd.core.lens import MM_PER_M

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
    def rms_depth_mm(self) -> float:
        """RMS depth residual over the depths used."""
        r = np.asarray(self.residual_depth_mm)[np.asarray(self.used)]
        return float(np.sqrt(np.mean(r * r)))


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
    # σ of P from the vertex's σ in counts through the local slope of a first straight fit.
    slope = abs(np.polyfit(u, power, 1)[0])
    sigma_p = np.maximum(slope * np.asarray(sigma_counts) / (hi - lo), 1e-9)
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


# -- private helpers --------------------------------------------------------------------------
def _fit_model(
    u: FloatArray, p: FloatArray, s: FloatArray, span: tuple[float, float], f: float
) -> tuple[FocusModel, float]:
    """Polynomial (degree by leave-one-out, at most MAX_BASE_DEGREE), with a residual spline
    where that predicts the left-out depths better; and its leave-one-out error (dioptres)."""
    degree, _ = _choose_degree(u, p, s, MAX_BASE_DEGREE)

    def build(mask: FloatArray, spline: bool) -> FocusModel:
        coef = tuple(float(c) for c in _polyfit(u[mask], p[mask], s[mask], degree))
        base = FocusModel(coef, *span, f)
        return _with_spline(base, u[mask], p[mask], s[mask]) if spline else base

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
