"""Compiled kernels of the measurements' statistics (numba, ``nogil``), bit for bit.

The focus cost (2) of a frame's per-normal peaks (:func:`focus_cost`: a trimmed mean and its
standard error) and the size invariant's autocovariances (:func:`slow_error_gammas`): each sums
in its NumPy twin's order (:mod:`dffd.core.kernels_stats_numpy`: NumPy's pairwise sums, Python's
left-to-right ones), so the values are the same to the last bit. Split from
:mod:`dffd.core.kernels_track`; :mod:`dffd.core.kernels` re-exports them, dispatched with the
trackers' kernels.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import jit as _jit

__all__ = ["focus_cost", "slow_error_gammas"]

FloatArray = npt.NDArray[np.float64]

_V = "float64[::1]"


# -- the focus cost (2) of a frame (dffd.core.focus.focus_cost) ---------------------------------
@_jit(f"float64({_V}, int64, int64)")
def _pairwise_sum(a: FloatArray, lo: int, n: int) -> float:
    """``np.add.reduce(a[lo:lo + n])`` bit for bit: NumPy's pairwise summation, which a plain
    loop does not reproduce. A block of up to 128 values: a plain loop below 8, else eight
    running sums, combined pairwise, then the rest; above 128 the halving tree (at a multiple
    of 8), evaluated here with an explicit stack, left before right."""
    f_lo = np.empty(64, dtype=np.int64)
    f_n = np.empty(64, dtype=np.int64)
    f_stage = np.zeros(64, dtype=np.int64)
    values = np.empty(64)
    sp, vp = 1, 0
    f_lo[0], f_n[0] = lo, n
    while sp > 0:
        top = sp - 1
        seg_lo, seg_n = f_lo[top], f_n[top]
        if seg_n <= 128:
            if seg_n < 8:
                res = 0.0
                for i in range(seg_n):
                    res += a[seg_lo + i]
            else:
                r0, r1, r2, r3 = a[seg_lo], a[seg_lo + 1], a[seg_lo + 2], a[seg_lo + 3]
                r4, r5, r6, r7 = a[seg_lo + 4], a[seg_lo + 5], a[seg_lo + 6], a[seg_lo + 7]
                i = 8
                while i < seg_n - (seg_n % 8):
                    b = seg_lo + i
                    r0 += a[b]
                    r1 += a[b + 1]
                    r2 += a[b + 2]
                    r3 += a[b + 3]
                    r4 += a[b + 4]
                    r5 += a[b + 5]
                    r6 += a[b + 6]
                    r7 += a[b + 7]
                    i += 8
                res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
                while i < seg_n:
                    res += a[seg_lo + i]
                    i += 1
            values[vp] = res
            vp += 1
            sp -= 1
            continue
        half = seg_n // 2
        half -= half % 8
        if f_stage[top] == 0:
            f_stage[top] = 1
            f_lo[sp], f_n[sp], f_stage[sp] = seg_lo, half, 0
            sp += 1
        elif f_stage[top] == 1:
            f_stage[top] = 2
            f_lo[sp], f_n[sp], f_stage[sp] = seg_lo + half, seg_n - half, 0
            sp += 1
        else:
            values[vp - 2] = values[vp - 2] + values[vp - 1]
            vp -= 1
            sp -= 1
    return float(values[0])


@_jit(f"int64({_V}, float64, {_V})")
def focus_cost(peak_sq: FloatArray, trim_fraction: float, out: FloatArray) -> int:
    """Cost (2) from the per-normal max ``||∇I||²`` (NaN = no edge) into ``out`` = (g, σ_g);
    returns 1, or 0 when there is none. The NumPy twin's operations (its trimmed mean and
    standard error: the same sorted values, the same pairwise sums), so the same values."""
    n = 0
    for v in peak_sq:
        if math.isfinite(v):
            n += 1
    if n < 8:
        return 0
    vals = np.empty(n)
    n = 0
    for v in peak_sq:
        if math.isfinite(v):
            vals[n] = v
            n += 1
    vals.sort()
    cut = int(trim_fraction * n)
    lo, k = (cut, n - 2 * cut) if n - 2 * cut >= 4 else (0, n)
    mean = _pairwise_sum(vals, lo, k) / k
    if mean <= 0:
        return 0
    dev = np.empty(k)
    for i in range(k):
        d = vals[lo + i] - mean
        dev[i] = d * d
    se = math.sqrt(_pairwise_sum(dev, 0, k) / (k - 1)) / math.sqrt(k)
    g = 1.0 / mean
    out[0] = g
    out[1] = g * se / mean
    return 1


# -- the size invariant's autocovariances (dffd.core.noise.SlowErrors) --------------------------
@_jit(f"void({_V}, {_V}, int64, {_V})")
def slow_error_gammas(x: FloatArray, s: FloatArray, lags: int, gamma: FloatArray) -> None:
    """``gamma[j] = Σ_k r_k r_{k−j} / n`` for ``j = 0 … lags`` of the residuals ``r_k = (x_k −
    m)/s_k`` about the weighted mean ``m = Σ (x/s²) / Σ (1/s²)``: every sum left to right, as
    the NumPy twin's Python sums (the same values bit for bit; ~1 µs instead of ~50 µs a burst
    in the core's loop)."""
    n = x.shape[0]
    w_sum = 0.0
    for k in range(n):
        w_sum += 1.0 / (s[k] * s[k])
    mean = 0.0
    for k in range(n):
        mean += x[k] / (s[k] * s[k])
    mean /= w_sum
    r = np.empty(n)
    for k in range(n):
        r[k] = (x[k] - mean) / s[k]
    for j in range(lags + 1):
        acc = 0.0
        for k in range(j, n):
            acc += r[k] * r[k - j]
        gamma[j] = acc / n
