"""Compiled kernels of the contour tracker's pass (numba, ``nogil``).

A pass works on 64-element arrays, where NumPy's per-call overhead (~1-5 µs a call, ~60 calls a
pass) was the whole cost; the kernels do the same arithmetic in one call each. They mirror the
NumPy reference in tests/test_core_contour.py operation for operation (float32 where it was
float32), so results agree to rounding (~1e-12 relative; the test asserts 1e-9).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import CacheReport, cache_report
from dffd.core.kernel_jit import jit as _jit
from dffd.core.kernel_layout import (  # shared with the NumPy twins (kernels_numpy)
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
from dffd.core.kernels_track import (  # the 3D tracker's kernels, dispatched with these
    track_combine,
    track_predict,
    track_size_update,
    track_unit_update,
)

__all__ = [
    "CacheReport",
    "cache_report",
    "edge_moments",
    "fit_pass",
    "normals_and_box",
    "sample_maps",
    "track_combine",
    "track_predict",
    "track_size_update",
    "track_unit_update",
]

FloatArray = npt.NDArray[np.float64]

# numba types of the kernels' arrays (all C-contiguous)
_M, _M32, _V = "float64[:, ::1]", "float32[:, ::1]", "float64[::1]"


@_jit(f"UniTuple(float64, 4)({_M}, {_M})")
def normals_and_box(pts: FloatArray, normals: FloatArray) -> tuple[float, float, float, float]:
    """outward_normals(pts) into ``normals``; returns the bounding box (xmin, ymin, xmax, ymax)."""
    n = pts.shape[0]
    area2 = 0.0
    xmin = xmax = pts[0, 0]
    ymin = ymax = pts[0, 1]
    for i in range(n):
        nx_i = (i + 1) % n
        pv = (i - 1) % n
        tx = pts[nx_i, 0] - pts[pv, 0]
        ty = pts[nx_i, 1] - pts[pv, 1]
        norm = math.sqrt(ty * ty + tx * tx)
        norm = max(norm, 1e-12)
        normals[i, 0] = ty / norm
        normals[i, 1] = -tx / norm
        area2 += pts[i, 0] * pts[nx_i, 1] - pts[nx_i, 0] * pts[i, 1]
        xmin = min(xmin, pts[i, 0])
        xmax = max(xmax, pts[i, 0])
        ymin = min(ymin, pts[i, 1])
        ymax = max(ymax, pts[i, 1])
    if 0.5 * area2 >= 0:  # counter-clockwise in image coordinates (y down): flip to outward
        for i in range(n):
            normals[i, 0] = -normals[i, 0]
            normals[i, 1] = -normals[i, 1]
    return xmin, ymin, xmax, ymax


@_jit(f"void({_M}, {_M}, int64, float64, float64, {_M32}, {_M32})")
def sample_maps(  # noqa: PLR0917 - numba kernels take positional arguments
    pts: FloatArray,
    normals: FloatArray,
    s: int,
    x0: float,
    y0: float,
    mapx: npt.NDArray[np.float32],
    mapy: npt.NDArray[np.float32],
) -> None:
    """Sample positions along every normal, −s … s px, in window coordinates (float32)."""
    for i in range(pts.shape[0]):
        for j in range(2 * s + 1):
            step = float(j - s)
            mapx[i, j] = np.float32(pts[i, 0] + step * normals[i, 0] - x0)
            mapy[i, j] = np.float32(pts[i, 1] + step * normals[i, 1] - y0)


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


@_jit(
    f"void({_M32}, {_M32}, {_M}, float64, int64, {_V}, {_V}, float64, float64, float64, int64, "
    f"float64, {_V}, {_V}, {_V})"
)
def edge_moments(  # noqa: PLR0917 - numba kernels take positional arguments
    bx: npt.NDArray[np.float32],
    by: npt.NDArray[np.float32],
    normals: FloatArray,
    polarity: float,
    s: int,
    offset: FloatArray,
    inlier: FloatArray,
    sigma2_hint: float,
    k_sigma: float,
    min_half: float,
    passes: int,
    trim_fraction: float,
    var_out: FloatArray,
    mass_out: FloatArray,
    pooled: FloatArray,
) -> None:
    """Second moment of the edge-derivative profile along every inlier normal (focus measure).

    Profile ``p_j = −polarity · (∇I · n)`` at ``x_j = j − s`` px. A window of half-width ``W``
    (linear taper over the last pixel, so the moment is continuous in the centre and in ``W``)
    is centred on the edge, re-centred once on the profile's centroid ``μ``; the moment is
    ``Σ w p (x − μ)² / Σ w p``. Blur variances add under convolution whatever the PSF's shape,
    so this grows as ``σ0² + c (v0 − v)²`` exactly where the peak of ``p`` does not. ``W`` starts
    at the whole line and becomes ``k_sigma`` times the mass-weighted mean spread of the frame
    (one blur for the whole target) for ``passes`` passes; the first window is ``k_sigma``
    times the square root of ``sigma2_hint`` (the log-parabola edge width of the shape fit:
    a Gaussian's, only a starting point) when it is finite. A normal whose window would leave the
    sampled line, or whose profile has no positive mass, gives NaN. ``pooled`` gets the focus
    cost (g, σ_g): the mass-weighted mean of the moments after dropping ``trim_fraction`` of the
    normals at each end of the sorted moments, and its standard error (NaN with < 8 normals) —
    the same as ``dffd.core.focus.edge_variance_cost``.
    """
    n = offset.shape[0]
    half = float(s) - 0.5
    if math.isfinite(sigma2_hint) and sigma2_hint > 0.0:
        half = max(min(k_sigma * math.sqrt(sigma2_hint), half), min_half)
    prof = np.zeros((n, 2 * s + 1))  # the edge-derivative profiles, computed once
    for i in range(n):
        var_out[i] = np.nan
        mass_out[i] = np.nan
        if inlier[i] != 0:
            nx = normals[i, 0] * -polarity
            ny = normals[i, 1] * -polarity
            for j in range(2 * s + 1):
                prof[i, j] = float(bx[i, j]) * nx + float(by[i, j]) * ny
    for k in range(passes):
        final = k == passes - 1
        num = 0.0
        den = 0.0
        for i in range(n):
            var_out[i] = np.nan
            mass_out[i] = np.nan
            if inlier[i] == 0:
                continue
            c = offset[i]
            mu = c
            m0 = 0.0
            m2 = 0.0
            good = True
            hw = half
            for step in range(2):  # centre on the peak, then on the centroid
                if abs(c) + hw > s - 0.5 + 1e-9:
                    if final:  # a truncated window would bias the moment: drop the normal
                        good = False
                        break
                    hw = s - 0.5 - abs(c)  # the adaptation passes only need a rough spread
                    if hw < min_half:
                        good = False
                        break
                lo = c - hw
                hi = c + hw
                m0 = 0.0
                m1 = 0.0
                m2 = 0.0
                j0 = max(math.floor(lo), -s)
                j1 = min(math.ceil(hi), s)
                for x in range(j0, j1 + 1):
                    w = min(max(hw + 0.5 - abs(x - c), 0.0), 1.0)
                    if w <= 0.0:
                        continue
                    p = w * prof[i, x + s]
                    d = x - c
                    m0 += p
                    m1 += p * d
                    m2 += p * d * d
                if m0 <= 0.0:
                    good = False
                    break
                mu = c + m1 / m0
                if step == 0:
                    c = mu
            if not good:
                continue
            # the last pass's moments are about its window centre c; move them to its centroid
            d0 = mu - c
            v = m2 / m0 - d0 * d0
            if v <= 0.0:
                continue
            var_out[i] = v
            mass_out[i] = m0
            num += m0 * v
            den += m0
        if den <= 0.0:
            break
        half = max(min(k_sigma * math.sqrt(num / den), float(s) - 0.5), min_half)
    pooled[0] = np.nan
    pooled[1] = np.nan
    m = 0
    for i in range(n):
        if math.isfinite(var_out[i]):
            m += 1
    if m < 8:
        return
    values = np.empty(m)
    index = np.empty(m, dtype=np.int64)
    m = 0
    for i in range(n):
        if math.isfinite(var_out[i]):
            values[m] = var_out[i]
            index[m] = i
            m += 1
    order = np.arange(m)  # insertion sort by moment (stable, ≤ 64 items)
    for q in range(1, m):
        key = order[q]
        r = q - 1
        while r >= 0 and values[order[r]] > values[key]:
            order[r + 1] = order[r]
            r -= 1
        order[r + 1] = key
    cut = int(trim_fraction * m)
    lo = cut if m - 2 * cut >= 4 else 0
    hi = m - cut if m - 2 * cut >= 4 else m
    total = 0.0
    acc = 0.0
    for q in range(lo, hi):
        i = index[order[q]]
        total += mass_out[i]
        acc += mass_out[i] * var_out[i]
    if total <= 0.0:
        return
    g = acc / total
    k = hi - lo
    dev2 = 0.0
    for q in range(lo, hi):
        i = index[order[q]]
        d = (var_out[i] - g) * mass_out[i]
        dev2 += d * d
    pooled[0] = g
    pooled[1] = math.sqrt(dev2 * k / (k - 1)) / total
