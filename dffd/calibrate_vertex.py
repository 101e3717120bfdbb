"""The closed loop's reading of a calibration sweep: where a burst bracket settles (dffd calibrate).

The estimator fits a parabola through three settings ``c − h, c, c + h`` and re-centres the next
bracket on its vertex; it settles where that vertex is its own centre, i.e. where the bracket's
two ends cost the same, ``g(c − h) = g(c + h)`` (the middle setting's cost drops out). For a
cost that is an even function of defocus (a Gaussian or a disc blur) that is the sharpest
setting; for one that is not (an aberrated lens, whose caustic lowers the cost on one side of
focus only) it is not, and it is not where a least-squares parabola over the whole ± h window
has its vertex either (docs/estimation.md §13: +7.0 against +3.3 µm of v from the RMS focus on
the aberrated optics). A table calibrated on this reading makes the closed loop read the
calibrated depth whatever the point-spread function (:func:`closed_loop_vertex`).

The sweep's costs are smoothed locally (a weighted quadratic through the ``2k + 1`` settings
nearest each evaluation point, ``k`` chosen by leave-one-out cross-validation on the settings
around the bracket's ends), the three-point fit of the estimator
(:func:`dffd.core.focus.fit_burst`) is iterated on the smoothed curve until its vertex is its
centre. Where the bracket meets an end of the focus range the estimator shifts it, not shrinks
it (:func:`dffd.core.focus.plan_burst`), and so does this reading: the result is then the
three-point vertex of the pinned bracket (a target beyond ~11 m, whose ``v − h`` lies beyond
infinity focus). A sweep that does not reach the bracket gives None (the caller falls back to
the least-squares vertex, :func:`dffd.calibrate_parabola.fit_vertex`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core.lens import Lens, VertexResponse

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

# Half-widths (settings either side) the local quadratic may use; chosen per sweep by
# leave-one-out cross-validation. From 5 settings (the fewest a quadratic with a residual check
# needs) to 11 (about ± 0.6 h on a 41-setting sweep over ± 2 h: wider would smooth across the
# cost's change of curvature at the bracket's ends).
SMOOTH_HALF_POINTS = (2, 3, 4, 5)
# The settings that choose the smoothing and scale its σ: within this fraction of h of either
# end of the first bracket (where the reading looks).
CV_REACH_H = 0.5
FIXED_POINT_ITERATIONS = 60  # the map contracts by |1 − slope| ≈ 0.15 a step: ~8 suffice
FIXED_POINT_TOLERANCE_H = 1e-6  # converged when the centre moves less than this × h
OUTLIER_SIGMA = 4.0  # a setting beyond this many robust σ of its neighbours' fit is dropped
MAD_TO_SIGMA = 1.4826  # σ of a normal distribution per median absolute deviation
# The vertex response (table_response): true offsets (h) at which it is read. A sweep spans
# ~ ± 2 h around its minimum (41 settings), so a bracket ± h around centres up to ~ ± 1 h off
# the fixed point stays inside it at most depths; the closed loop's offsets spread ± 0.1-0.3 h.
RESPONSE_OFFSETS_H = tuple(round(0.1 * i, 1) for i in range(-12, 13))
RESPONSE_MIN_DEPTHS = 3  # sweeps an offset needs to be pooled
RESPONSE_MIN_OFFSETS = 5  # offsets the pooled response needs (± 0.2 h at least)


@dataclass(frozen=True, slots=True)
class LoopReading:
    """Where the closed loop reads a sweep: its vertex ``x`` and σ (the sweep's axis), the
    bracket centre it settled on (≠ x only when pinned at an end) and the smoothing used."""

    x: float
    sigma: float
    centre: float
    pinned: bool  # the bracket met an end of the focus range and was shifted
    half_points: int  # the local quadratic's half-width (settings)
    noise_scale: float  # the smoother's residual rms over the settings' own σ (≥ 1)
    n_dropped: int
    # per true offset δ asked for (``offsets_h``): the three-point vertex the estimator fits on
    # the smoothed sweep with its bracket centred at x − δ h, as (v̂ − centre)/h; NaN where that
    # bracket leaves the sweep; empty when pinned or not asked
    response_h: tuple[float, ...] = ()


def closed_loop_vertex(
    x: npt.ArrayLike,
    g: npt.ArrayLike,
    sigma_g: npt.ArrayLike,
    half_width: float,
    *,
    start: float,
    ends: tuple[float, float] = (-math.inf, math.inf),
    offsets_h: Sequence[float] = (),
) -> LoopReading | None:
    """The closed loop's reading of the costs ``g`` (σ ``sigma_g``) at settings ``x``.

    ``half_width``: the estimator's half-bracket h in ``x``'s units; ``start``: a first centre
    (the least-squares vertex); ``ends``: the focus range's ends in ``x`` (the bracket is
    shifted to stay inside). None when the sweep does not cover the bracket or has no minimum.
    ``offsets_h``: true offsets (in h, from the fixed point) at which to read the vertex
    response on the same smoothed curve (``LoopReading.response_h``).
    """
    xs = np.asarray(x, dtype=np.float64)
    gs = np.asarray(g, dtype=np.float64)
    ss = np.asarray(sigma_g, dtype=np.float64)
    order = np.argsort(xs)
    xs, gs, ss = xs[order], gs[order], ss[order]
    ok = np.isfinite(xs) & np.isfinite(gs) & np.isfinite(ss)
    xs, gs, ss = xs[ok], gs[ok], np.maximum(ss[ok], 1e-12 * np.abs(gs[ok]).max(initial=1.0))
    h = float(half_width)
    if len(xs) < 2 * SMOOTH_HALF_POINTS[0] + 1 or not h > 0:
        return None
    lo_end, hi_end = min(ends), max(ends)
    if hi_end - lo_end < 2 * h:
        return None

    def clamp(c: float) -> float:
        return min(max(c, lo_end + h), hi_end - h)

    centre = clamp(float(start))
    near = (np.abs(xs - (centre - h)) <= CV_REACH_H * h) | (
        np.abs(xs - (centre + h)) <= CV_REACH_H * h
    )
    keep = np.ones(len(xs), dtype=bool)
    k, scale = _choose_smoothing(xs, gs, ss, keep, near)
    # settings far off their neighbours' fit (a frame with a lost contour …) are dropped once
    resid = _loo_residuals(xs, gs, ss, keep, k=k, at=near)
    robust = MAD_TO_SIGMA * float(np.median(np.abs(resid[near]))) if near.any() else 0.0
    bad = near & (np.abs(resid) > OUTLIER_SIGMA * max(robust, 1.0))
    if bad.any():
        keep &= ~bad
        k, scale = _choose_smoothing(xs, gs, ss, keep, near & keep)
    xk, gk, sk = xs[keep], gs[keep], ss[keep]
    result = None
    for _ in range(FIXED_POINT_ITERATIONS):
        if centre - h < xk[0] - 1e-9 * h or centre + h > xk[-1] + 1e-9 * h:
            return None
        weights = [_smoother_weights(xk, sk, at, k) for at in (centre - h, centre, centre + h)]
        gm, g0, gp = (float(w @ gk) for w in weights)
        den = 2.0 * (gm - 2.0 * g0 + gp)
        if den <= 0:
            return None
        vertex = centre + h * (gm - gp) / den
        result = (vertex, centre, weights, gm, gp, den)
        nxt = clamp(vertex)
        if abs(nxt - centre) < FIXED_POINT_TOLERANCE_H * h:
            break
        centre = nxt
    else:
        return None
    assert result is not None
    vertex, centre, weights, gm, gp, den = result
    # σ of the three-point vertex at the settled bracket, first order in the costs
    n = gm - gp
    d_m = h * (1.0 / den - 2.0 * n / den**2)
    d_0 = h * 4.0 * n / den**2
    d_p = h * (-1.0 / den - 2.0 * n / den**2)
    w = d_m * weights[0] + d_0 * weights[1] + d_p * weights[2]
    sigma = math.sqrt(float(np.sum((w * sk) ** 2))) * scale
    pinned = abs(vertex - centre) > 1e3 * FIXED_POINT_TOLERANCE_H * h
    response: tuple[float, ...] = ()
    if offsets_h and not pinned:
        # on the smoothing that found the fixed point, so that the response is 0 at δ = 0 and
        # the correction leaves the closed loop's fixed point (the table's) where it is. The
        # least smoothing (5 settings) flattens the bend at the sharp setting less (reference
        # optics, pooled slope within ± 0.3 h 1.079 against 1.071) but reads +0.001 h at δ = 0:
        # a shift of every vertex by 0.09 µm of v, +2.5 mm of bias on the reference circle
        # (ss bias 1.2 -> 3.7 mm, LPV ss RMS 7.4 -> 9.9 mm: a shift in v is a bias ∝ z²)
        response = tuple(_three_point(xk, gk, sk, k, c=vertex - d * h, h=h) for d in offsets_h)
    return LoopReading(vertex, sigma, centre, pinned, k, scale, int((~keep).sum()), response)


def table_response(
    lens: Lens,
    sweeps: Sequence[tuple[float, Sequence[tuple[float, float, float]]]],
    measure: str,
    outer_blur_px: float,
    default_f_number: float,
) -> tuple[VertexResponse | None, list[str]]:
    """The vertex response of the burst fit, measured on the calibration's sweeps through the
    calibrated table ``lens`` (the v axis the estimator uses), pooled over the depths; and
    the lines that report it (per depth and pooled; why none).

    ``sweeps``: (depth m, ((counts, g, σ_g), …)) per sweep; ``outer_blur_px``: the burst
    planner's bracket (its half-width h = that blur's v offset). Each sweep is read where the
    closed loop settles (:func:`closed_loop_vertex`) and, on the same smoothed curve, the
    three-point vertex for brackets centred RESPONSE_OFFSETS_H half-brackets off it. Pinned
    sweeps (beyond ~11 m) and offsets whose bracket leaves a sweep are not used; an offset needs
    RESPONSE_MIN_DEPTHS depths. The pooled response is the median over the depths at each
    offset, restricted to the contiguous run of offsets around 0 that have enough; None (no
    correction) when fewer than RESPONSE_MIN_OFFSETS remain or it is not increasing.
    """
    n_f = lens.f_number if lens.f_number is not None else default_f_number
    per_px = lens.pixel_pitch_mm * n_f * 2.0 / lens.focal_length_mm  # as plan_burst
    h_rel = per_px * outer_blur_px
    ends = lens.v_range_mm
    offsets = np.asarray(RESPONSE_OFFSETS_H)
    rows: list[FloatArray] = []
    depths: list[float] = []
    for z_m, sweep in sweeps:
        if len(sweep) < 2 * SMOOTH_HALF_POINTS[0] + 1:
            continue
        c, g, s = (np.asarray(col, dtype=np.float64) for col in zip(*sweep, strict=True))
        v = lens.v_from_counts_array(c)
        ok = np.isfinite(v)
        if ok.sum() < 2 * SMOOTH_HALF_POINTS[0] + 1:
            continue
        v, g, s = v[ok], g[ok], s[ok]
        start = float(v[int(np.argmin(g))])
        reading = closed_loop_vertex(
            v, g, s, h_rel * start, start=start, ends=ends, offsets_h=RESPONSE_OFFSETS_H
        )
        if reading is None or reading.pinned:
            continue
        rows.append(np.asarray(reading.response_h))
        depths.append(z_m)
    lines: list[str] = []
    if len(rows) < RESPONSE_MIN_DEPTHS:
        lines.append(f"vertex response: {len(rows)} sweeps read (< {RESPONSE_MIN_DEPTHS}): none")
        return None, lines
    table = np.vstack(rows)
    counted = np.isfinite(table).sum(axis=0)
    pooled = np.array([
        float(np.median(col[np.isfinite(col)])) if n else math.nan
        for col, n in zip(table.T, counted, strict=True)
    ])  # fmt: skip
    enough = counted >= RESPONSE_MIN_DEPTHS
    centre = int(np.argmin(np.abs(offsets)))
    lo = hi = centre
    while lo > 0 and enough[lo - 1]:
        lo -= 1
    while hi < len(offsets) - 1 and enough[hi + 1]:
        hi += 1
    use = slice(lo, hi + 1)
    t, f = offsets[use], pooled[use]
    dev = table[:, use] - f
    spread = float(np.sqrt(np.nanmean(dev * dev)))
    lines.append(
        f"vertex response ({measure}, bracket ± {outer_blur_px:g} px of blur): "
        f"{len(rows)} sweeps, offsets {t[0]:+.2f} … {t[-1]:+.2f} h, spread between sweeps "
        f"{spread:.4f} h rms"
    )
    for z_m, row in zip(depths, rows, strict=True):
        lines.append(
            f"  z = {z_m:6.2f} m: slope {_slope(offsets, row, 0.3):.3f} (± 0.3 h), "
            f"{_slope(offsets, row, 0.9):.3f} (± 0.9 h); fitted at ± 0.6 h "
            f"{_at(offsets, row, -0.6):+.3f} / {_at(offsets, row, 0.6):+.3f} h"
        )
    lines.append(
        f"  pooled: slope {_slope(t, f, 0.3):.3f} (± 0.3 h), {_slope(t, f, 0.9):.3f} (± 0.9 h)"
    )
    if len(t) < RESPONSE_MIN_OFFSETS or not bool(np.all(np.diff(f) > 0)):
        lines.append("  not increasing, or too few offsets: no correction written")
        return None, lines
    response = VertexResponse(
        measure=measure,
        half_width_rel=h_rel,
        true_h=tuple(float(x) for x in t),
        fitted_h=tuple(round(float(x), 6) for x in f),
        depth_spread_h=round(spread, 6),
        n_depths=len(rows),
    )
    return response, lines


# -- private helpers --------------------------------------------------------------------------
def _three_point(
    x: FloatArray, g: FloatArray, s: FloatArray, k: int, *, c: float, h: float
) -> float:
    """(v̂ − c)/h of the three-point fit at c − h, c, c + h on the smoothed curve; NaN where the
    bracket leaves the settings or the parabola has no minimum."""
    if c - h < x[0] - 1e-9 * h or c + h > x[-1] + 1e-9 * h:
        return math.nan
    gm, g0, gp = (float(_smoother_weights(x, s, at, k) @ g) for at in (c - h, c, c + h))
    den = 2.0 * (gm - 2.0 * g0 + gp)
    return (gm - gp) / den if den > 0 else math.nan


def _slope(offsets: FloatArray, fitted: FloatArray, reach: float) -> float:
    """Least-squares slope of the fitted offsets on the true ones within ± ``reach`` h."""
    sel = (np.abs(offsets) <= reach + 1e-9) & np.isfinite(fitted)
    if sel.sum() < 2:
        return math.nan
    return float(np.polyfit(offsets[sel], fitted[sel], 1)[0])


def _at(offsets: FloatArray, fitted: FloatArray, x: float) -> float:
    i = int(np.argmin(np.abs(offsets - x)))
    return float(fitted[i])


def _smoother_weights(x: FloatArray, s: FloatArray, at: float, k: int) -> FloatArray:
    """Weights w with smoothed g(at) = w · g: a weighted quadratic through the 2k + 1 settings
    nearest ``at``."""
    idx = np.argsort(np.abs(x - at), kind="stable")[: 2 * k + 1]
    t = x[idx] - at
    scale = max(float(np.abs(t).max()), 1e-300)  # conditioning: t in [-1, 1]
    t = t / scale
    design = np.stack([np.ones_like(t), t, t * t], axis=1) / s[idx, None]
    # the first row of the pseudo-inverse: (AᵀA)⁻¹ e₀ mapped through Aᵀ
    try:
        y = np.linalg.solve(design.T @ design, np.array([1.0, 0.0, 0.0]))
    except np.linalg.LinAlgError:
        y = np.linalg.pinv(design.T @ design) @ np.array([1.0, 0.0, 0.0])
    w = np.zeros(len(x))
    w[idx] = (design @ y) / s[idx]
    return w


def _loo_residuals(
    x: FloatArray, g: FloatArray, s: FloatArray, keep: BoolArray, *, k: int, at: BoolArray
) -> FloatArray:
    """At the settings ``at``: the cost less the local quadratic of the other kept settings, in
    its σ (NaN elsewhere)."""
    out = np.full(len(x), np.nan)
    for i in np.flatnonzero(at):
        others = keep.copy()
        others[i] = False
        if others.sum() < 2 * k + 1:
            continue
        w = _smoother_weights(x[others], s[others], float(x[i]), k)
        out[i] = (g[i] - float(w @ g[others])) / s[i]
    return out


def _choose_smoothing(
    x: FloatArray, g: FloatArray, s: FloatArray, keep: BoolArray, near: BoolArray
) -> tuple[int, float]:
    """The half-width with the smallest leave-one-out error at the ``near`` settings, and that
    error's rms in the settings' σ (≥ 1: it scales the reading's σ)."""
    best = (SMOOTH_HALF_POINTS[0], math.inf)
    for k in SMOOTH_HALF_POINTS:
        r = _loo_residuals(x, g, s, keep, k=k, at=near)[near]
        r = r[np.isfinite(r)]
        if len(r) == 0:
            continue
        mse = float(np.mean(r * r))
        if mse < best[1]:
            best = (k, mse)
    k, mse = best
    return k, max(1.0, math.sqrt(mse)) if math.isfinite(mse) else 1.0
