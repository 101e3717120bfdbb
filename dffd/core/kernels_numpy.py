"""NumPy twins of the tracker's compiled kernels, for the seconds before numba has compiled them.

Same names, signatures, arrays and results (to rounding: the tests compare both on the same
inputs) as :mod:`dffd.core.kernels`, written with vectorised NumPy instead of loops: importing
this module compiles nothing (the bilinear samples are OpenCV's remap, which the compiled
kernel reproduces). They cost a few hundred µs a pass more than the compiled kernels
(NumPy's per-call overhead on 64-element arrays; docs/design.md §10 has the figures), which is
why they only bridge the start: :mod:`dffd.core.kernel_dispatch` swaps the compiled kernels in
as soon as they are ready.
"""

from __future__ import annotations

import math
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.kernel_layout import (
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
    S_INTERIOR,
    S_OFFSET,
    S_PEAK,
    S_RES,
    S_VALID,
    S_W,
    S_WIDTH2,
    ST_BOX,
    ST_FAILED,
    ST_HAS_WINDOW,
    ST_KEPT,
    ST_NEED_WINDOW,
    ST_PASSES,
    TINY,
)
from dffd.core.kernels_stats_numpy import (  # the measurements' statistics, dispatched too
    focus_cost,  # the focus cost (2)
    slow_error_gammas,  # the size invariant's autocovariances (noise.SlowErrors)
)
from dffd.core.kernels_track_numpy import (  # the 3D tracker's twins, dispatched with these
    cartesian_point,  # a direction and depth as a world point (tracking3d), too
    track_combine,
    track_predict,
    track_size_update,
    track_unit_update,
)

__all__ = [
    "acquire_mask",
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
F32Array = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]
# sample coordinates beyond this (or NaN) are outside any window (as in the compiled kernel)
_HUGE = 1e9


def normals_and_box(pts: FloatArray, normals: FloatArray) -> tuple[float, float, float, float]:
    """outward_normals(pts) into ``normals``; returns the bounding box (xmin, ymin, xmax, ymax)."""
    nxt = np.roll(pts, -1, axis=0)
    tangent = nxt - np.roll(pts, 1, axis=0)
    tx, ty = tangent[:, 0], tangent[:, 1]
    norm = np.maximum(np.sqrt(ty * ty + tx * tx), 1e-12)
    normals[:, 0] = ty / norm
    normals[:, 1] = -tx / norm
    area2 = float(np.sum(pts[:, 0] * nxt[:, 1] - nxt[:, 0] * pts[:, 1]))
    if 0.5 * area2 >= 0:  # counter-clockwise in image coordinates (y down): flip to outward
        np.negative(normals, out=normals)
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def acquire_mask(
    gray: npt.NDArray[np.uint8], x0: int, y0: int, downscale: int, out: npt.NDArray[np.uint8]
) -> float:
    """Otsu's threshold of the region at (x0, y0) of ``gray`` (``out``'s shape × ``downscale``,
    area-averaged to ``out``'s shape) smoothed 5×5 (σ = 1); the mask into ``out``."""
    h, w = out.shape
    region = gray[y0 : y0 + h * downscale, x0 : x0 + w * downscale]
    if downscale > 1:
        region = np.asarray(cv2.resize(region, (w, h), interpolation=cv2.INTER_AREA), np.uint8)
    patch = cv2.GaussianBlur(region, (5, 5), 1.0)
    thresh, binary = cv2.threshold(patch, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    out[...] = binary
    return float(thresh)


def sobel_pair(b: F32Array, gx: F32Array, gy: F32Array) -> None:
    """OpenCV's 3x3 Sobel of ``b`` (scale 1/8) along x into ``gx`` and along y into ``gy``."""
    cv2.Sobel(b, cv2.CV_32F, 1, 0, dst=gx, ksize=3, scale=0.125)
    cv2.Sobel(b, cv2.CV_32F, 0, 1, dst=gy, ksize=3, scale=0.125)


def sample_normals(  # noqa: PLR0917 - the compiled kernels' positional signature
    gx: F32Array,
    gy: F32Array,
    x0: float,
    y0: float,
    pts: FloatArray,
    normals: FloatArray,
    s: int,
    bx: F32Array,
    by: F32Array,
) -> None:
    """Bilinear samples of the gradient window along every normal (see kernels.sample_normals):
    ``cv2.remap`` itself, whose values the compiled kernel reproduces."""
    steps = np.arange(-s, s + 1, dtype=np.float64)[None, :]
    mapx = (pts[:, 0:1] + steps * normals[:, 0:1] - x0).astype(np.float32)
    mapy = (pts[:, 1:2] + steps * normals[:, 1:2] - y0).astype(np.float32)
    finite = (np.abs(mapx) < _HUGE) & (np.abs(mapy) < _HUGE)
    if not finite.all():  # NaN or far outside: a point outside the window, samples 0
        mapx[~finite] = -2.0
        mapy[~finite] = -2.0
    if gx.size == 0:
        bx[:] = 0.0
        by[:] = 0.0
        return
    bx[:] = cv2.remap(gx, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    by[:] = cv2.remap(gy, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def fit_passes(  # noqa: PLR0917 - the compiled kernels' positional signature
    gx: F32Array,
    gy: F32Array,
    win: IntArray,
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
    state: IntArray,
    normals: FloatArray,
    bx: F32Array,
    by: F32Array,
    mag: F32Array,
    new_pts: FloatArray,
    peaks: FloatArray,
    scratch: FloatArray,
    design: FloatArray,
    out: FloatArray,
    fit: FloatArray,
) -> None:
    """The passes of one contour fit, resumable for a window (see kernels.fit_passes)."""
    k, kept = int(state[ST_PASSES]), int(state[ST_KEPT])
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
            state[ST_BOX : ST_BOX + 4] = (x0, y0, x1, y1)
            state[ST_PASSES], state[ST_KEPT] = k, kept
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
    state[ST_PASSES], state[ST_KEPT] = k, kept
    _fit_results(pts_in, new_pts[kept], out[kept, OUT_STATUS] == 0, fit)


def polarity(gray: npt.NDArray[np.uint8], pts: FloatArray, normals: FloatArray, d: float) -> float:
    """+1 when brighter ``d`` px inside than outside (median over normals; kernels.polarity)."""
    h, w = gray.shape
    both = np.concatenate((pts - d * normals, pts + d * normals)).astype(np.float32)
    finite = (np.abs(both) < _HUGE).all(axis=1)
    both[~finite] = 0.0
    fx, fy = np.floor(both[:, 0]), np.floor(both[:, 1])
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    a, b = (both[:, 0] - fx).astype(np.float64), (both[:, 1] - fy).astype(np.float64)
    x0, x1 = np.clip(ix, 0, w - 1), np.clip(ix + 1, 0, w - 1)
    y0, y1 = np.clip(iy, 0, h - 1), np.clip(iy + 1, 0, h - 1)
    g = gray.astype(np.float32)
    top = (a * (g[y0, x1] - g[y0, x0]).astype(np.float64) + g[y0, x0]).astype(np.float32)
    bot = (a * (g[y1, x1] - g[y1, x0]).astype(np.float64) + g[y1, x0]).astype(np.float32)
    val = (b * (bot - top).astype(np.float64) + top).astype(np.float32)
    val[~finite] = 0.0
    n = len(pts)
    diff = val[:n].astype(np.float64) - val[n:].astype(np.float64)
    return 1.0 if float(np.median(diff)) >= 0 else -1.0


def resample(points: FloatArray, out: FloatArray) -> None:
    """``len(out)`` points uniformly spaced in arc length along the closed polygon ``points``."""
    _resample(points, out)


def fit_pass(  # noqa: PLR0917 - the compiled kernels' positional signature
    bx: F32Array,
    by: F32Array,
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
    mag: F32Array,
    scratch: FloatArray,
    design: FloatArray,
    out: FloatArray,
) -> None:
    """Peak search along the normals, robust shape-space fit, new contour (see kernels.fit_pass)."""
    n = pts.shape[0]
    if has_window:
        _search(bx, by, normals, polarity, s, cfg, mag, scratch)
    else:
        scratch[S_OFFSET] = 0.0
        scratch[S_PEAK] = np.nan
        scratch[S_VALID] = 0.0
        scratch[S_WIDTH2] = np.nan
    offset, peak, width2 = scratch[S_OFFSET], scratch[S_PEAK], scratch[S_WIDTH2]
    valid = scratch[S_VALID] != 0
    # -- geometry about the centroid ---------------------------------------------------------
    c = pts.mean(axis=0)
    d = pts - c
    r_in = math.sqrt(float(np.sum(d * d)) / n)
    out[OUT_CX_IN], out[OUT_CY_IN], out[OUT_R_IN] = c[0], c[1], r_in
    scale = max(r_in, 1.0)
    k = _design(d / scale, normals, motion, design)
    a = design[:, :k]
    params, w, res = _irls(a, offset, valid)
    scratch[S_W], scratch[S_RES] = w, res
    inliers = valid & (np.abs(res) <= OUTLIER_PX) & (w > 0)
    scratch[S_INTERIOR] = inliers  # the inlier flags from here on (edge_moments reads them)
    n_in = int(np.count_nonzero(inliers))
    inlier_fraction = n_in / n
    out[OUT_INLIER_FRACTION] = inlier_fraction
    if inlier_fraction < cfg[2]:
        out[OUT_STATUS] = 1.0
        return
    out[OUT_STATUS] = 0.0
    # -- apply the motion (+ a fraction of the smoothed non-rigid residual) ------------------
    moved = pts + _motion_field(params, d / scale, motion)
    if relax > 0:
        resid = np.where(inliers, offset - a @ params, 0.0)
        sm = (np.roll(resid, 1) + 2 * resid + np.roll(resid, -1)) / 4.0
        moved += relax * sm[:, None] * normals
    _resample(moved, new_pts)
    # -- size, plausibility, edge width, residual --------------------------------------------
    c_new = new_pts.mean(axis=0)
    dn = new_pts - c_new
    r = math.sqrt(float(np.sum(dn * dn)) / n)
    inside = bool(
        new_pts.min() >= 0 and new_pts[:, 0].max() < width and new_pts[:, 1].max() < height
    )
    ok = inside and cfg[3] <= r <= cfg[4]
    w2 = width2[inliers & np.isfinite(width2)]
    edge_sigma2 = float(np.median(w2)) if len(w2) >= 8 else math.nan
    if cfg[5] != 0 and math.isfinite(edge_sigma2) and r > 0:
        r += edge_sigma2 / (2.0 * r)
    res_in = res[inliers]
    peaks[:] = np.where(inliers, peak, np.nan)
    out[OUT_OK] = 1.0 if ok else 0.0
    out[OUT_R] = r
    out[OUT_CX], out[OUT_CY] = c_new[0], c_new[1]
    out[OUT_RMS] = math.sqrt(float(res_in @ res_in) / n_in)
    out[OUT_EDGE_SIGMA2] = edge_sigma2


def edge_moments(  # noqa: PLR0917 - the compiled kernels' positional signature
    bx: F32Array,
    by: F32Array,
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

    The same windows, passes and pooling as ``kernels.edge_moments`` (its docstring has the
    method), all normals at once.
    """
    half = float(s) - 0.5
    if math.isfinite(sigma2_hint) and sigma2_hint > 0.0:
        half = max(min(k_sigma * math.sqrt(sigma2_hint), half), min_half)
    use = inlier != 0
    nx = normals[:, 0:1] * -polarity
    ny = normals[:, 1:2] * -polarity
    prof = np.where(use[:, None], bx.astype(np.float64) * nx + by.astype(np.float64) * ny, 0.0)
    x = np.arange(-s, s + 1, dtype=np.float64)[None, :]
    edge = float(s) - 0.5
    var_out[:] = np.nan
    mass_out[:] = np.nan
    for k in range(passes):
        final = k == passes - 1
        c = offset.copy()
        hw = np.full(len(offset), half)
        good = use.copy()
        mu = c.copy()
        m0 = m1 = m2 = np.zeros(len(offset))
        for step in range(2):  # centre on the peak, then on the centroid
            over = np.abs(c) + hw > edge + 1e-9
            if final:  # a truncated window would bias the moment: drop the normal
                good &= ~over
            else:  # the adaptation passes only need a rough spread
                hw = np.where(over, edge - np.abs(c), hw)
                good &= ~over | (hw >= min_half)
            wgt = np.clip(hw[:, None] + 0.5 - np.abs(x - c[:, None]), 0.0, 1.0)
            p = wgt * prof
            dx = x - c[:, None]
            m0 = p.sum(axis=1)
            m1 = (p * dx).sum(axis=1)
            m2 = (p * dx * dx).sum(axis=1)
            good &= m0 > 0.0
            with np.errstate(divide="ignore", invalid="ignore"):
                mu = np.where(good, c + m1 / np.where(good, m0, 1.0), c)
            if step == 0:
                c = mu
        with np.errstate(divide="ignore", invalid="ignore"):
            d0 = mu - c
            v = np.where(good, m2 / np.where(good, m0, 1.0) - d0 * d0, 0.0)
        good &= v > 0.0
        var_out[:] = np.where(good, v, np.nan)
        mass_out[:] = np.where(good, m0, np.nan)
        den = float(np.sum(m0[good]))
        if den <= 0.0:
            break
        num = float(np.sum(m0[good] * v[good]))
        half = max(min(k_sigma * math.sqrt(num / den), edge), min_half)
    pooled[0] = np.nan
    pooled[1] = np.nan
    finite = np.flatnonzero(np.isfinite(var_out))
    m = len(finite)
    if m < 8:
        return
    order = finite[np.argsort(var_out[finite], kind="stable")]
    cut = int(trim_fraction * m)
    if m - 2 * cut >= 4:
        order = order[cut : m - cut]
    mass = mass_out[order]
    var = var_out[order]
    total = float(np.sum(mass))
    if total <= 0.0:
        return
    g = float(np.sum(mass * var)) / total
    kept = len(order)
    dev = (var - g) * mass
    pooled[0] = g
    pooled[1] = math.sqrt(float(dev @ dev) * kept / (kept - 1)) / total


# -- helpers ---------------------------------------------------------------------------------


def _search(  # noqa: PLR0917 - the arrays of fit_pass
    bx: F32Array,
    by: F32Array,
    normals: FloatArray,
    polarity: float,
    s: int,
    cfg: FloatArray,
    mag: F32Array,
    scratch: FloatArray,
) -> None:
    """Per normal: sub-pixel max of |∇I|² of the target's polarity (log-parabola)."""
    n = len(normals)
    last = 2 * s
    n32 = normals.astype(np.float32) * np.float32(polarity)
    np.add(bx * bx, by * by, out=mag)
    mag[bx * n32[:, 0:1] + by * n32[:, 1:2] >= 0] = 0.0  # clutter edges of the other sign
    j = np.argmax(mag, axis=1)
    rows = np.arange(n)
    ym = mag[rows, np.maximum(j - 1, 0)].astype(np.float64)
    y0v = mag[rows, j].astype(np.float64)
    yp = mag[rows, np.minimum(j + 1, last)].astype(np.float64)
    interior = (j > 0) & (j < last)
    lm, l0, lp = np.log(ym + TINY), np.log(y0v + TINY), np.log(yp + TINY)
    denom = lm - 2 * l0 + lp
    good = interior & (denom < 0) & (ym > 0) & (yp > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.clip(np.where(good, 0.5 * (lm - lp) / denom, 0.0), -0.5, 0.5)
        scratch[S_WIDTH2] = np.where(good, -2.0 / denom, np.nan)  # ln|∇I|² = c − x²/σ²
    peak = np.where(good, np.exp(l0 - 0.25 * (lm - lp) * delta) - TINY, y0v)
    scratch[S_PEAK] = peak
    scratch[S_OFFSET] = (j - s) + delta
    scratch[S_INTERIOR] = interior
    med = float(np.median(peak[interior])) if interior.any() else 0.0
    threshold = max(cfg[0] * med, cfg[1] ** 2)
    scratch[S_VALID] = interior & (peak >= threshold)


def _design(d: FloatArray, normals: FloatArray, motion: int, design: FloatArray) -> int:
    """Normal displacement per unit motion parameter into ``design``; returns their number."""
    nx, ny = normals[:, 0], normals[:, 1]
    dx, dy = d[:, 0], d[:, 1]
    if motion == 0:
        design[:, 0], design[:, 1] = nx, ny
        return 2
    if motion == 1:  # δ = [[a, -b], [b, a]] d + t
        design[:, 0] = nx * dx + ny * dy
        design[:, 1] = ny * dx - nx * dy
        design[:, 2], design[:, 3] = nx, ny
        return 4
    design[:, 0], design[:, 1] = nx * dx, nx * dy
    design[:, 2], design[:, 3] = ny * dx, ny * dy
    design[:, 4], design[:, 5] = nx, ny
    return 6


def _irls(
    design: FloatArray, y: FloatArray, valid: BoolArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Huber-weighted least squares with a small ridge: (parameters, weights, residuals)."""
    k = design.shape[1]
    w = valid.astype(np.float64)
    params: FloatArray = np.zeros(k)
    yv = np.where(valid, y, 0.0)
    ridge = RIDGE * max(float(np.count_nonzero(valid)), 1.0) * np.eye(k)
    res = y.copy()
    for _ in range(IRLS_ITERATIONS):
        if np.count_nonzero(w) < k:
            break
        a = design * w[:, None]
        params = cast(FloatArray, np.linalg.solve(design.T @ a + ridge, a.T @ yv))
        res = y - design @ params
        absr = np.abs(res)
        w_new = np.where(valid, np.minimum(1.0, HUBER_K_PX / np.maximum(absr, 1e-12)), 0.0)
        w_new[absr > 2 * OUTLIER_PX] = 0.0
        if np.array_equal(w_new, w):  # the next solve would return the same parameters
            break
        w = w_new
    return params, w, res


def _motion_field(params: FloatArray, d: FloatArray, motion: int) -> FloatArray:
    """Displacement of every contour point (``d``: offsets from the centroid / scale)."""
    dx, dy = d[:, 0:1], d[:, 1:2]
    if motion == 0:
        return np.broadcast_to(params[:2], d.shape)
    if motion == 1:
        a, b, tx, ty = params
        return np.hstack([dx * a - dy * b + tx, dx * b + dy * a + ty])
    a11, a12, a21, a22, tx, ty = params
    return np.hstack([dx * a11 + dy * a12 + tx, dx * a21 + dy * a22 + ty])


def _resample(points: FloatArray, out: FloatArray) -> None:
    """``len(out)`` points uniformly spaced in arc length along the closed polygon ``points``."""
    closed = np.vstack([points, points[:1]])
    step = np.diff(closed, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])
    total = float(cum[-1])
    n = len(out)
    if total <= 0:
        out[:] = points[0]
        return
    s = np.arange(n) * (total / n)
    out[:, 0] = np.interp(s, cum, closed[:, 0])
    out[:, 1] = np.interp(s, cum, closed[:, 1])


def _fit_results(pts_in: FloatArray, kept: FloatArray, found: bool, fit: FloatArray) -> None:
    """fit_passes' float results (see kernels._fit_results)."""
    fit[FIT_CX_IN : FIT_CY_IN + 1] = np.add.reduce(pts_in, axis=0) / len(pts_in)
    if found:
        fit[FIT_XMIN], fit[FIT_YMIN] = kept.min(axis=0)
        fit[FIT_XMAX], fit[FIT_YMAX] = kept.max(axis=0)
    else:
        fit[FIT_XMIN : FIT_YMAX + 1] = np.nan
