"""Compiled kernels of the edges: the focus measure's second moments, the gradient's Sobel pair.

Split from :mod:`dffd.core.kernels` (which re-exports them with the tracker's pass kernels); their
NumPy twins are :func:`dffd.core.kernels_numpy.edge_moments` and
:func:`dffd.core.kernels_numpy.sobel_pair`.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import jit as _jit

__all__ = ["edge_moments", "sobel_pair"]

FloatArray = npt.NDArray[np.float64]

# numba types of the kernel's arrays (all C-contiguous)
_M, _M32, _V = "float64[:, ::1]", "float32[:, ::1]", "float64[::1]"
# Sobel 3x3's smoothing taps with the gradient's scale (1/8) folded in: powers of two, so every
# product is exact and only the order of the sums decides the rounding
_EIGHTH = np.float32(0.125)
_QUARTER = np.float32(0.25)


@_jit(f"void({_M32}, {_M32}, {_M32})")
def sobel_pair(
    b: npt.NDArray[np.float32], gx: npt.NDArray[np.float32], gy: npt.NDArray[np.float32]
) -> None:
    """``cv2.Sobel(b, CV_32F, 1, 0, ksize=3, scale=0.125)`` into ``gx`` and ``(0, 1)`` into
    ``gy``, bit for bit, in one pass over ``b`` (OpenCV's two calls read it twice).

    OpenCV filters a row with ``[-1, 0, 1]`` as one subtraction and with ``[1/8, 1/4, 1/8]`` as
    ``(p[-1] + p[1]) / 8 + p[0] / 4``, then the columns the same way (the scale goes to the
    smoothing taps); the border is reflected without repeating the edge (BORDER_REFLECT_101).
    """
    h, w = b.shape
    for y in range(h):
        ym = y - 1 if y > 0 else min(1, h - 1)
        yp = y + 1 if y < h - 1 else max(h - 2, 0)
        top = b[ym]
        mid = b[y]
        bot = b[yp]
        ox = gx[y]
        oy = gy[y]
        for x in range(1, w - 1):  # the interior: no branch, vectorised
            ox[x] = ((top[x + 1] - top[x - 1]) + (bot[x + 1] - bot[x - 1])) * _EIGHTH + (
                mid[x + 1] - mid[x - 1]
            ) * _QUARTER
            st = (top[x - 1] + top[x + 1]) * _EIGHTH + top[x] * _QUARTER
            sb = (bot[x - 1] + bot[x + 1]) * _EIGHTH + bot[x] * _QUARTER
            oy[x] = sb - st
        for x in (0, w - 1):  # the first and last columns, reflected
            xm = x - 1 if x > 0 else min(1, w - 1)
            xp = x + 1 if x < w - 1 else max(w - 2, 0)
            ox[x] = ((top[xp] - top[xm]) + (bot[xp] - bot[xm])) * _EIGHTH + (
                mid[xp] - mid[xm]
            ) * _QUARTER
            st = (top[xm] + top[xp]) * _EIGHTH + top[x] * _QUARTER
            sb = (bot[xm] + bot[xp]) * _EIGHTH + bot[x] * _QUARTER
            oy[x] = sb - st


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
