"""NumPy twins of the measurements' statistics kernels (:mod:`dffd.core.kernels_stats`).

Same names, signatures and values, bit for bit, as the compiled kernels (which sum in these
twins' order); they run while numba compiles (:mod:`dffd.core.kernel_dispatch`, through
:mod:`dffd.core.kernels_numpy`, which re-exports them). Split from
:mod:`dffd.core.kernels_track_numpy` with the kernels.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["focus_cost", "slow_error_gammas"]

FloatArray = npt.NDArray[np.float64]


def focus_cost(peak_sq: FloatArray, trim_fraction: float, out: FloatArray) -> int:
    """Cost (2) from per-normal max ``||∇I||²`` (NaN = no edge) into ``out`` = (g, σ_g);
    returns 1, or 0 when there is none (:func:`dffd.core.focus.focus_cost`)."""
    # One reduction per statistic on the kept values (this runs on every burst and tracking
    # frame): the same sums as ndarray.mean / .std(ddof=1), without their per-call overhead.
    vals = peak_sq[np.isfinite(peak_sq)]
    n = len(vals)
    if n < 8:
        return 0
    vals.sort()
    cut = int(trim_fraction * n)
    kept = vals[cut : n - cut] if n - 2 * cut >= 4 else vals
    k = len(kept)
    mean = float(np.add.reduce(kept)) / k
    if mean <= 0:
        return 0
    dev = kept - mean
    dev *= dev
    se = math.sqrt(float(np.add.reduce(dev)) / (k - 1)) / math.sqrt(k)
    g = 1.0 / mean
    out[0] = g
    out[1] = g * se / mean
    return 1


def slow_error_gammas(x: FloatArray, s: FloatArray, lags: int, gamma: FloatArray) -> None:
    """The autocovariances of the size invariant's normalised residuals into ``gamma``
    (:func:`dffd.core.kernels_stats.slow_error_gammas`): Python sums left to right, the
    kernel's values bit for bit."""
    xs, ss = x.tolist(), s.tolist()
    n = len(xs)
    w_sum = sum(1.0 / (si * si) for si in ss)
    mean = sum(xi / (si * si) for xi, si in zip(xs, ss, strict=True)) / w_sum
    r = [(xi - mean) / si for xi, si in zip(xs, ss, strict=True)]
    for j in range(lags + 1):
        gamma[j] = sum(r[k] * r[k - j] for k in range(j, n)) / n
