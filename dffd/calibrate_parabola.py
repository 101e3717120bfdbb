"""The least-squares vertex of one focus sweep of ``dffd calibrate``: a weighted parabola on a
window symmetric about the vertex.

Pure numerics (no rig, no I/O). The costs at each setting are averages of several frames (σ from
their spread). The parabola is fitted on a window *symmetric about the vertex* that reaches out
to where the cost has risen by :data:`WINDOW_RISE` × its minimum — the blur of a burst's outer
settings (~3 px), where a focus cost is still parabolic in ``v``, and far enough out that a flat
bottom (a blur below a pixel changes no measure) or a local wiggle cannot pull the vertex. The
window is re-centred on the fitted vertex until it stops moving (an off-centre window of a cost
that is not exactly a parabola biases the vertex); points more than :data:`OUTLIER_SIGMA` robust
σ off the parabola are dropped (:func:`fit_vertex`). The sweep's settings are in counts; the fit
runs in whatever axis it is given — ``v`` through the provisional focus model on the second pass
(:func:`dffd.calibrate_fit.fit_table`), as the estimator's own burst fit does. :func:`vertex` is
the plain parabola through the few points around the minimum.

Split from :mod:`dffd.calibrate_fit` (:func:`fit_vertex`) and :mod:`dffd.calibrate`
(:func:`vertex`); where the estimator's closed loop reads a sweep is :mod:`dffd.calibrate_vertex`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

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
FIT_HALF_WIDTH = 3  # points either side of the minimum used by vertex() (the coarse peak)


@dataclass(frozen=True, slots=True)
class VertexFit:
    """The sharpest setting of one sweep: the vertex, its σ and the window it was fitted on."""

    x: float
    sigma: float
    window: tuple[float, float]
    n_used: int
    n_dropped: int


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


def vertex(counts: npt.NDArray[np.float64], costs: npt.NDArray[np.float64]) -> float:
    """Counts of the vertex of a parabola through the costs around their minimum."""
    i = int(np.argmin(costs))
    lo, hi = max(0, i - FIT_HALF_WIDTH), min(len(costs), i + FIT_HALF_WIDTH + 1)
    x, y = counts[lo:hi], costs[lo:hi]
    if len(x) < 3:
        return float(counts[i])
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    if a <= 0:
        return float(counts[i])
    return float(np.clip(-b / (2 * a) + x.mean(), x.min(), x.max()))


# -- private helpers --------------------------------------------------------------------------
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
