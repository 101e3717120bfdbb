"""Compiled kernels of the contour tracker's pass (numba, ``nogil``).

A pass works on 64-element arrays, where NumPy's per-call overhead (~1-5 µs a call, ~60 calls a
pass) was the whole cost; the kernels do the same arithmetic in one call each. They mirror the
NumPy reference in tests/test_core_contour.py operation for operation (float32 where it was
float32), so results agree to rounding (~1e-12 relative; the test asserts 1e-9).

Here: the peak search and robust fit of a pass (:func:`fit_pass`) and of a whole fit
(:func:`fit_passes`), the arc-length resampling and the polarity (it takes the fit's median); the
normals and the samples along them are :mod:`dffd.core.kernels_sample`'s. This module is the
compiled kernel set :mod:`dffd.core.kernel_dispatch` loads: it re-exports those and the
acquisition's, edges', 3D tracker's and statistics' kernels (the twins: kernels_numpy).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import CacheReport, cache_report
from dffd.core.kernel_jit import jit as _jit
from dffd.core.kernel_layout import (  # shared with the NumPy twins (kernels_numpy)
    FIT_CX_IN,
    FIT_CY_IN,
    FIT_XMAX,
    FIT_XMIN,
    FIT_YMAX,
    FIT_YMIN,
    HUBER_K_PX,
    IRLS_ITERATIONS,
    OUT_CX,
    OUT_CX_IN,
    OUT_CY,
    OUT_CY_IN,
    OUT_EDGE_SIGMA2,
    OUT_INLIER_FRACTION,
    OUT_OK,
    OUT_R,
    OUT_R_IN,
    OUT_RMS,
    OUT_STATUS,
    OUTLIER_PX,
    RIDGE,
    ST_BOX,
    ST_FAILED,
    ST_HAS_WINDOW,
    ST_KEPT,
    ST_NEED_WINDOW,
    ST_PASSES,
)
from dffd.core.kernel_layout import S_INTERIOR as _S_INTERIOR
from dffd.core.kernel_layout import S_OFFSET as _S_OFFSET
from dffd.core.kernel_layout import S_PEAK as _S_PEAK
from dffd.core.kernel_layout import S_RES as _S_RES
from dffd.core.kernel_layout import S_TMP as _S_TMP
from dffd.core.kernel_layout import S_TMP2 as _S_TMP2
from dffd.core.kernel_layout import S_VALID as _S_VALID
from dffd.core.kernel_layout import S_W as _S_W
from dffd.core.kernel_layout import S_WIDTH2 as _S_WIDTH2
from dffd.core.kernel_layout import S_WNEW as _S_WNEW
from dffd.core.kernel_layout import TINY as _TINY
from dffd.core.kernels_acquire import acquire_mask  # the acquisition's mask, dispatched too
from dffd.core.kernels_edges import (  # the focus measure's and the gradient's, dispatched too
    edge_moments,
    sobel_pair,
)
from dffd.core.kernels_sample import normals_and_box, sample_normals  # dispatched too
from dffd.core.kernels_sample import sample_u8 as _sample_u8  # polarity's, not dispatched
from dffd.core.kernels_stats import (  # the measurements' statistics, dispatched too
    focus_cost,  # the focus cost (2)
    slow_error_gammas,  # the size invariant's autocovariances (noise.SlowErrors)
)
from dffd.core.kernels_track import (  # the 3D tracker's kernels, dispatched with these
    cartesian_point,  # a direction and depth as a world point (tracking3d), too
    track_combine,
    track_predict,
    track_size_update,
    track_unit_update,
)

__all__ = [
    "CacheReport",
    "acquire_mask",
    "cache_report",
    "cartesian_point",
    "edge_moments",
    "fit_pass",
    "fit_passes",
    "focus_cost",
    "normals_and_box",
    "polarity",
    "resample",
    "sample_normals",
    "slow_error_gammas",
    "sobel_pair",
    "track_combine",
    "track_predict",
    "track_size_update",
    "track_unit_update",
]

FloatArray = npt.NDArray[np.float64]

# numba types of the kernels' arrays (all C-contiguous)
_M, _M32, _V = "float64[:, ::1]", "float32[:, ::1]", "float64[::1]"
_T, _T32, _I = "float64[:, :, ::1]", "float32[:, :, ::1]", "int64[::1]"


@_jit(f"int64({_M}, {_M}, float64, float64, float64, int64, {_M})")
def _kernel_design(  # noqa: PLR0917 - numba kernels take positional arguments
    pts: FloatArray,
    normals: FloatArray,
    cx: float,
    cy: float,
    scale: float,
    motion: int,
    design: FloatArray,
) -> int:
    """Normal displacement per unit motion parameter into ``design``; returns their number."""
    for i in range(pts.shape[0]):
        nx = normals[i, 0]
        ny = normals[i, 1]
        dx = (pts[i, 0] - cx) / scale
        dy = (pts[i, 1] - cy) / scale
        if motion == 0:
            design[i, 0] = nx
            design[i, 1] = ny
        elif motion == 1:  # δ = [[a, -b], [b, a]] d + t
            design[i, 0] = nx * dx + ny * dy
            design[i, 1] = ny * dx - nx * dy
            design[i, 2] = nx
            design[i, 3] = ny
        else:
            design[i, 0] = nx * dx
            design[i, 1] = nx * dy
            design[i, 2] = ny * dx
            design[i, 3] = ny * dy
            design[i, 4] = nx
            design[i, 5] = ny
    return 2 if motion == 0 else (4 if motion == 1 else 6)


@_jit(f"float64({_V})")
def _kernel_median(values: FloatArray) -> float:
    """np.median of a small 1-D array (same value)."""
    v = np.sort(values)
    m = len(v) // 2
    return float(v[m]) if len(v) % 2 else float((v[m - 1] + v[m]) / 2.0)


@_jit(f"void({_M}, {_M})")
def _kernel_resample(points: FloatArray, out: FloatArray) -> None:
    """resample_closed(points, len(out)) into ``out``."""
    m = points.shape[0]
    n = out.shape[0]
    cum = np.empty(m + 1)
    xs = np.empty(m + 1)
    ys = np.empty(m + 1)
    cum[0] = 0.0
    for i in range(m + 1):
        xs[i] = points[i % m, 0]
        ys[i] = points[i % m, 1]
        if i > 0:
            cum[i] = cum[i - 1] + math.hypot(xs[i] - xs[i - 1], ys[i] - ys[i - 1])
    total = cum[m]
    if total <= 0:
        for i in range(n):
            out[i, 0] = points[0, 0]
            out[i, 1] = points[0, 1]
        return
    s = np.empty(n)
    for i in range(n):
        s[i] = i * (total / n)
    out[:, 0] = np.interp(s, cum, xs)
    out[:, 1] = np.interp(s, cum, ys)


resample = _kernel_resample  # public: ContourTracker.start resamples the acquisition polygon


@_jit(f"void({_M}, {_V}, int64, {_V})")
def _kernel_solve(a: FloatArray, b: FloatArray, k: int, x: FloatArray) -> None:
    """x[:k] = solve(a[:k, :k], b[:k]) by Gaussian elimination with partial pivoting."""
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if piv != col:
            for c in range(k):
                a[col, c], a[piv, c] = a[piv, c], a[col, c]
            b[col], b[piv] = b[piv], b[col]
        for r in range(col + 1, k):
            f = a[r, col] / a[col, col]
            for c in range(col, k):
                a[r, c] -= f * a[col, c]
            b[r] -= f * b[col]
    for r in range(k - 1, -1, -1):
        acc = b[r]
        for c in range(r + 1, k):
            acc -= a[r, c] * x[c]
        x[r] = acc / a[r, r]


@_jit(f"void({_M}, int64, {_V}, {_V}, {_M}, {_V})")
def _kernel_irls(  # noqa: PLR0917 - numba kernels take positional arguments
    design: FloatArray,
    k: int,
    y: FloatArray,
    valid: FloatArray,
    scratch: FloatArray,
    params: FloatArray,
) -> None:
    """Huber-weighted least squares with a small ridge (weights, residuals into ``scratch``).

    Stops early when the weights repeat: the next solve would return the same parameters (on a
    clean edge every residual is below the Huber threshold and one re-weighting settles it).
    """
    n = design.shape[0]
    w = scratch[_S_W]
    w_new = scratch[_S_WNEW]
    res = scratch[_S_RES]
    n_valid = 0
    for i in range(n):
        w[i] = valid[i]
        res[i] = y[i]
        if valid[i] != 0:
            n_valid += 1
    ridge = RIDGE * max(float(n_valid), 1.0)
    a = np.empty((6, 6))
    b = np.empty(6)
    for _ in range(IRLS_ITERATIONS):
        nz = 0
        for i in range(n):
            if w[i] != 0:
                nz += 1
        if nz < k:
            break
        for p in range(k):
            b[p] = 0.0
            for q in range(k):
                a[p, q] = 0.0
        for i in range(n):
            wi = w[i]
            if wi == 0:
                continue
            yi = y[i] if valid[i] != 0 else 0.0
            for p in range(k):
                dp = design[i, p] * wi
                b[p] += dp * yi
                for q in range(k):
                    a[q, p] += design[i, q] * dp
        for p in range(k):
            a[p, p] += ridge
        _kernel_solve(a, b, k, params)
        same = True
        for i in range(n):
            fit = 0.0
            for c in range(k):
                fit += design[i, c] * params[c]
            res[i] = y[i] - fit
            absr = abs(res[i])
            wn = 0.0
            if valid[i] != 0:
                wn = min(1.0, HUBER_K_PX / max(absr, 1e-12))
            if absr > 2 * OUTLIER_PX:
                wn = 0.0
            w_new[i] = wn
            if wn != w[i]:
                same = False
        if same:
            break
        for i in range(n):
            w[i] = w_new[i]


@_jit(
    f"void({_M32}, {_M32}, boolean, {_M}, {_M}, float64, int64, int64, float64, {_V}, int64, "
    f"int64, {_M}, {_V}, {_M32}, {_M}, {_M}, {_V})"
)
def fit_pass(  # noqa: PLR0917 - numba kernels take positional arguments
    bx: npt.NDArray[np.float32],
    by: npt.NDArray[np.float32],
    has_window: bool,
    pts: FloatArray,
    normals: FloatArray,
    polarity: float,
    s: int,
    motion: int,
    relax: float,
    cfg: FloatArray,
    width: int,
    height: int,
    new_pts: FloatArray,
    peaks: FloatArray,
    mag: npt.NDArray[np.float32],
    scratch: FloatArray,
    design: FloatArray,
    out: FloatArray,
) -> None:
    """Peak search along the normals, robust shape-space fit, new contour (see _step)."""
    n = pts.shape[0]
    last = 2 * s
    offset = scratch[_S_OFFSET]
    peak = scratch[_S_PEAK]
    valid = scratch[_S_VALID]
    width2 = scratch[_S_WIDTH2]
    interior = scratch[_S_INTERIOR]
    tmp = scratch[_S_TMP]
    # -- per normal: sub-pixel max of |∇I|² of the target's polarity (log-parabola) --------
    if has_window:
        pol = np.float32(polarity)
        n_int = 0
        for i in range(n):
            nx32 = np.float32(normals[i, 0]) * pol
            ny32 = np.float32(normals[i, 1]) * pol
            jbest = 0
            best = np.float32(0.0)
            for j in range(last + 1):
                gx = bx[i, j]
                gy = by[i, j]
                m = gx * gx + gy * gy
                if gx * nx32 + gy * ny32 >= 0:
                    m = np.float32(0.0)  # clutter edges of the other sign are ignored
                mag[i, j] = m
                if j == 0 or m > best:
                    best = m
                    jbest = j
            jm = max(jbest - 1, 0)
            jp = min(jbest + 1, last)
            ym = float(mag[i, jm])
            y0v = float(mag[i, jbest])
            yp = float(mag[i, jp])
            inner = 0 < jbest < last
            lm = math.log(ym + _TINY)
            l0 = math.log(y0v + _TINY)
            lp = math.log(yp + _TINY)
            denom = lm - 2 * l0 + lp
            delta = 0.0
            if inner and denom < 0 and ym > 0 and yp > 0:
                delta = min(max(0.5 * (lm - lp) / denom, -0.5), 0.5)
                width2[i] = -2.0 / denom  # ln|∇I|² = c − x²/σ²: Δ² = −2/σ²
                peak[i] = math.exp(l0 - 0.25 * (lm - lp) * delta) - _TINY
            else:
                width2[i] = np.nan
                peak[i] = y0v
            offset[i] = (jbest - s) + delta
            interior[i] = 1.0 if inner else 0.0
            if inner:
                tmp[n_int] = peak[i]
                n_int += 1
        med = _kernel_median(tmp[:n_int]) if n_int > 0 else 0.0
        threshold = max(cfg[0] * med, cfg[1] ** 2)
        for i in range(n):
            valid[i] = 1.0 if interior[i] != 0 and peak[i] >= threshold else 0.0
    else:
        for i in range(n):
            offset[i] = 0.0
            peak[i] = np.nan
            valid[i] = 0.0
            width2[i] = np.nan
    # -- geometry about the centroid ---------------------------------------------------------
    cx = 0.0
    cy = 0.0
    for i in range(n):
        cx += pts[i, 0]
        cy += pts[i, 1]
    cx /= n
    cy /= n
    ss = 0.0
    for i in range(n):
        dx = pts[i, 0] - cx
        dy = pts[i, 1] - cy
        ss += dx * dx + dy * dy
    out[OUT_CX_IN] = cx
    out[OUT_CY_IN] = cy
    out[OUT_R_IN] = math.sqrt(ss / n)
    scale = max(math.sqrt(ss / n), 1.0)
    k = _kernel_design(pts, normals, cx, cy, scale, motion, design)
    params = np.zeros(6)
    _kernel_irls(design, k, offset, valid, scratch, params)
    w = scratch[_S_W]
    res = scratch[_S_RES]
    n_in = 0
    for i in range(n):
        inl = valid[i] != 0 and abs(res[i]) <= OUTLIER_PX and w[i] > 0
        interior[i] = 1.0 if inl else 0.0  # reused: inlier flag from here on
        if inl:
            n_in += 1
    inliers = interior
    inlier_fraction = n_in / n
    out[OUT_INLIER_FRACTION] = inlier_fraction
    if inlier_fraction < cfg[2]:
        out[OUT_STATUS] = 1.0
        return
    out[OUT_STATUS] = 0.0
    # -- apply the motion (+ a fraction of the smoothed non-rigid residual) ------------------
    moved = np.empty((n, 2))
    for i in range(n):
        dx = (pts[i, 0] - cx) / scale
        dy = (pts[i, 1] - cy) / scale
        if motion == 0:
            mx = params[0]
            my = params[1]
        elif motion == 1:
            mx = dx * params[0] + dy * -params[1] + params[2]
            my = dx * params[1] + dy * params[0] + params[3]
        else:
            mx = dx * params[0] + dy * params[1] + params[4]
            my = dx * params[2] + dy * params[3] + params[5]
        moved[i, 0] = pts[i, 0] + mx
        moved[i, 1] = pts[i, 1] + my
    if relax > 0:
        resid = scratch[_S_TMP2]
        for i in range(n):
            shift = 0.0
            for c in range(k):
                shift += design[i, c] * params[c]
            resid[i] = offset[i] - shift if inliers[i] != 0 else 0.0
        for i in range(n):
            sm = (resid[(i - 1) % n] + 2 * resid[i] + resid[(i + 1) % n]) / 4.0
            moved[i, 0] = moved[i, 0] + relax * sm * normals[i, 0]
            moved[i, 1] = moved[i, 1] + relax * sm * normals[i, 1]
    _kernel_resample(moved, new_pts)
    # -- size, plausibility, edge width, residual --------------------------------------------
    c0 = 0.0
    c1 = 0.0
    for i in range(n):
        c0 += new_pts[i, 0]
        c1 += new_pts[i, 1]
    c0 /= n
    c1 /= n
    ss = 0.0
    ok = True
    for i in range(n):
        dx = new_pts[i, 0] - c0
        dy = new_pts[i, 1] - c1
        ss += dx * dx + dy * dy
        x = new_pts[i, 0]
        y = new_pts[i, 1]
        if x < 0 or y < 0 or x >= width or y >= height:
            ok = False
    r = math.sqrt(ss / n)
    ok = ok and cfg[3] <= r <= cfg[4]
    n_w = 0
    for i in range(n):
        if inliers[i] != 0 and math.isfinite(width2[i]):
            tmp[n_w] = width2[i]
            n_w += 1
    edge_sigma2 = _kernel_median(tmp[:n_w]) if n_w >= 8 else np.nan
    if cfg[5] != 0 and math.isfinite(edge_sigma2) and r > 0:
        r += edge_sigma2 / (2.0 * r)
    rss = 0.0
    for i in range(n):
        if inliers[i] != 0:
            rss += res[i] * res[i]
            peaks[i] = peak[i]
        else:
            peaks[i] = np.nan
    out[OUT_OK] = 1.0 if ok else 0.0
    out[OUT_R] = r
    out[OUT_CX] = c0
    out[OUT_CY] = c1
    out[OUT_RMS] = math.sqrt(rss / n_in)
    out[OUT_EDGE_SIGMA2] = edge_sigma2


@_jit(f"void({_M}, {_M}, boolean, {_V})")
def _fit_results(pts_in: FloatArray, kept: FloatArray, found: bool, fit: FloatArray) -> None:
    """fit_passes' float results: the box of ``kept`` (NaN unless ``found``), the centroid of
    ``pts_in`` (the same sums as fit_pass's, so the same value as its OUT_CX_IN)."""
    n = pts_in.shape[0]
    cx = 0.0
    cy = 0.0
    for i in range(n):
        cx += pts_in[i, 0]
        cy += pts_in[i, 1]
    fit[FIT_CX_IN] = cx / n
    fit[FIT_CY_IN] = cy / n
    xmin = ymin = xmax = ymax = np.nan
    if found:
        xmin = xmax = kept[0, 0]
        ymin = ymax = kept[0, 1]
        for i in range(n):
            xmin = min(xmin, kept[i, 0])
            xmax = max(xmax, kept[i, 0])
            ymin = min(ymin, kept[i, 1])
            ymax = max(ymax, kept[i, 1])
    fit[FIT_XMIN] = xmin
    fit[FIT_YMIN] = ymin
    fit[FIT_XMAX] = xmax
    fit[FIT_YMAX] = ymax


@_jit(
    f"void({_M32}, {_M32}, {_I}, {_M}, float64, int64, int64, float64, {_V}, int64, int64, "
    f"int64, float64, int64, {_I}, {_T}, {_T32}, {_T32}, {_M32}, {_T}, {_M}, {_T}, {_M}, {_M}, "
    f"{_V})"
)
def fit_passes(  # noqa: PLR0917 - numba kernels take positional arguments
    gx: npt.NDArray[np.float32],
    gy: npt.NDArray[np.float32],
    win: npt.NDArray[np.int64],
    pts_in: FloatArray,
    polarity: float,
    s: int,
    motion: int,
    relax: float,
    cfg: FloatArray,
    width: int,
    height: int,
    max_passes: int,
    refine_px: float,
    margin: int,
    state: npt.NDArray[np.int64],
    normals: FloatArray,
    bx: npt.NDArray[np.float32],
    by: npt.NDArray[np.float32],
    mag: npt.NDArray[np.float32],
    new_pts: FloatArray,
    peaks: FloatArray,
    scratch: FloatArray,
    design: FloatArray,
    out: FloatArray,
    fit: FloatArray,
) -> None:
    """The passes of one contour fit from ``pts_in`` (see ContourTracker._fit), in one call.

    Each pass: normals, the samples of the gradient window ``win`` (x0, y0, x1, y1 in the frame;
    ``gx``, ``gy`` its values) along them, :func:`fit_pass`. Passes go on while the last one
    moved the contour by more than ``refine_px`` (centroid shift + |Δr|), at most
    ``max_passes``; a pass that fails after the first stops them and the last good one is kept
    (``state``: :data:`~dffd.core.kernel_layout.ST_KEPT` names its buffer). A pass whose
    points ± ``margin`` leave the window stops the call with ``ST_NEED_WINDOW`` set and the box
    it needs in ``ST_BOX``: the caller computes that window and calls again with the same
    ``state`` to resume. ``fit`` receives the box of the kept contour and the centroid of
    ``pts_in`` (:data:`~dffd.core.kernel_layout.FIT_XMIN` …).
    """
    k = state[ST_PASSES]
    kept = state[ST_KEPT]
    state[ST_NEED_WINDOW] = 0
    while k < max_passes:
        b = 0 if kept < 0 else 1 - kept
        src = pts_in if k == 0 else new_pts[kept]
        xmin, ymin, xmax, ymax = normals_and_box(src, normals[b])
        x0 = max(math.floor(xmin) - margin, 0)
        y0 = max(math.floor(ymin) - margin, 0)
        x1 = min(math.ceil(xmax) + margin + 1, width)
        y1 = min(math.ceil(ymax) + margin + 1, height)
        has_window = x1 - x0 >= 4 and y1 - y0 >= 4
        if has_window and (x0 < win[0] or y0 < win[1] or x1 > win[2] or y1 > win[3]):
            state[ST_NEED_WINDOW] = 1
            state[ST_BOX] = x0
            state[ST_BOX + 1] = y0
            state[ST_BOX + 2] = x1
            state[ST_BOX + 3] = y1
            state[ST_PASSES] = k
            state[ST_KEPT] = kept
            return
        if has_window:
            sample_normals(gx, gy, float(win[0]), float(win[1]), src, normals[b], s, bx[b], by[b])
        state[ST_HAS_WINDOW + b] = 1 if has_window else 0
        fit_pass(
            bx[b], by[b], has_window, src, normals[b], polarity, s, motion, relax, cfg, width,
            height, new_pts[b], peaks[b], mag, scratch[b], design, out[b],
        )  # fmt: skip
        k += 1
        found = out[b, OUT_STATUS] == 0 and out[b, OUT_OK] != 0
        if kept >= 0 and not found:
            state[ST_FAILED] = 1  # the refinement failed: the pass before it is kept
            break
        kept = b
        if not found:
            break
        moved = math.hypot(out[b, OUT_CX] - out[b, OUT_CX_IN], out[b, OUT_CY] - out[b, OUT_CY_IN])
        if moved + abs(out[b, OUT_R] - out[b, OUT_R_IN]) <= refine_px:
            break
    state[ST_PASSES] = k
    state[ST_KEPT] = kept
    _fit_results(pts_in, new_pts[kept], out[kept, OUT_STATUS] == 0, fit)


@_jit(f"float64(uint8[:, ::1], {_M}, {_M}, float64)")
def polarity(gray: npt.NDArray[np.uint8], pts: FloatArray, normals: FloatArray, d: float) -> float:
    """+1 when the image is brighter ``d`` px inside the contour than outside (median over the
    normals), else −1: bilinear samples as ``cv2.remap`` (float32 coordinates, replicated
    border; see :func:`sample_normals`) of ``pts ∓ d·normals``."""
    n = pts.shape[0]
    diff = np.empty(n)
    h, w = gray.shape
    for i in range(n):
        inner = _sample_u8(gray, pts[i, 0] - d * normals[i, 0], pts[i, 1] - d * normals[i, 1], w, h)
        outer = _sample_u8(gray, pts[i, 0] + d * normals[i, 0], pts[i, 1] + d * normals[i, 1], w, h)
        diff[i] = float(inner) - float(outer)
    return 1.0 if _kernel_median(diff) >= 0 else -1.0
