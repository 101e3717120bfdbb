"""Compiled kernel of the acquisition search's mask (numba, ``nogil``): OpenCV's values, one pass.

:func:`dffd.core.acquisition.find_target` thresholds a smoothed copy of the searched region with
Otsu's threshold: ``cv2.resize(INTER_AREA)`` by 2 for a whole frame, ``cv2.GaussianBlur`` 5×5
σ = 1, ``cv2.threshold(THRESH_OTSU)``. The three calls read and write the region four times and
OpenCV's Otsu histogram is a scalar loop; this kernel does the same integer arithmetic in one
call with the same results bit for bit (the 8-bit resize and blur are exact integer filters in
OpenCV, and the threshold is the same sequence of double operations over the histogram). Split
from :mod:`dffd.core.kernels`, which re-exports it; its NumPy twin is
:func:`dffd.core.kernels_numpy.acquire_mask` (the three OpenCV calls).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import jit as _jit

__all__ = ["BLUR_TAPS_Q8", "acquire_mask"]

# cv2.GaussianBlur(uint8, (5, 5), 1.0)'s bit-exact taps, in 1/256: OpenCV rounds the Gaussian
# (13.95, 62.52, 103.07, ...) so that the taps sum to 256 exactly; rows then columns, integer
# sums, rounded half up at the end (>> 16). Checked against OpenCV in tests/test_kernels_numpy.py.
BLUR_TAPS_Q8 = (14, 62, 104, 62, 14)
_K0, _K1, _K2 = np.int32(BLUR_TAPS_Q8[0]), np.int32(BLUR_TAPS_Q8[1]), np.int32(BLUR_TAPS_Q8[2])
_HALF = np.int32(1 << 15)
# OpenCV's Otsu skips the levels where either class holds less than FLT_EPSILON of the pixels
_FLT_EPSILON = float(np.finfo(np.float32).eps)


# (helpers first: the kernels compile when this module is imported)
@_jit("int64(int64, int64)")
def _reflect(i: int, n: int) -> int:
    """Index ``i`` of a row of ``n`` reflected into it without repeating the edge (n >= 2)."""
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


@_jit("float64(int64[::1], int64)")
def _otsu(hist: npt.NDArray[np.int64], total: int) -> float:
    """OpenCV's Otsu threshold of 8-bit levels from their counts, the same double operations
    in the same order (``getThreshVal_Otsu``)."""
    h = np.empty(256)
    mu = 0.0
    scale = 1.0 / total
    for i in range(256):
        h[i] = hist[i]
        mu += i * float(hist[i])
    mu *= scale
    mu1 = 0.0
    q1 = 0.0
    max_sigma = 0.0
    max_val = 0.0
    for i in range(256):
        p_i = h[i] * scale
        mu1 *= q1
        q1 += p_i
        q2 = 1.0 - q1
        if min(q1, q2) < _FLT_EPSILON or max(q1, q2) > 1.0 - _FLT_EPSILON:
            continue
        mu1 = (mu1 + i * p_i) / q1
        mu2 = (mu - q1 * mu1) / q2
        sigma = q1 * q2 * (mu1 - mu2) * (mu1 - mu2)
        if sigma > max_sigma:
            max_sigma = sigma
            max_val = float(i)
    return max_val


@_jit("float64(uint8[:, ::1], int64, int64, int64, uint8[:, ::1])")
def acquire_mask(
    gray: npt.NDArray[np.uint8], x0: int, y0: int, downscale: int, out: npt.NDArray[np.uint8]
) -> float:
    """Otsu's threshold of the region of ``gray`` at (``x0``, ``y0``) smoothed (and halved when
    ``downscale`` is 2), and the mask (255 above it, else 0) into ``out`` ((h, w) of the
    smoothed copy, at least 3×3; the region is ``downscale`` times that).

    The same values as ``cv2.threshold(cv2.GaussianBlur(r, (5, 5), 1.0), 0, 255,
    THRESH_BINARY + THRESH_OTSU)`` with ``r = cv2.resize(region, (w, h), INTER_AREA)`` when
    ``downscale`` is 2 (``region`` cropped to twice ``out``'s shape), ``r = region`` when 1.
    """
    h, w = out.shape
    small = np.empty((h, w), dtype=np.uint8)
    if downscale == 2:  # INTER_AREA by 2: the 2×2 mean, rounded half up
        for y in range(h):
            r0 = gray[y0 + 2 * y, x0:]
            r1 = gray[y0 + 2 * y + 1, x0:]
            row = small[y]
            for x in range(w):
                row[x] = (
                    np.int32(r0[2 * x]) + np.int32(r0[2 * x + 1])
                    + np.int32(r1[2 * x]) + np.int32(r1[2 * x + 1]) + np.int32(2)
                ) >> np.int32(2)  # fmt: skip
    else:
        for y in range(h):
            small[y] = gray[y0 + y, x0 : x0 + w]
    # the 5×5 blur, border reflected without repeating the edge (BORDER_REFLECT_101): the rows
    # first (at most 255 · 256: uint16), then the columns (int32), rounded half up
    rows = np.empty((h, w), dtype=np.uint16)
    for y in range(h):
        src = small[y]
        dst = rows[y]
        for x in range(2, w - 2):
            dst[x] = (
                _K0 * (np.int32(src[x - 2]) + np.int32(src[x + 2]))
                + _K1 * (np.int32(src[x - 1]) + np.int32(src[x + 1]))
                + _K2 * np.int32(src[x])
            )
        for x in (0, 1, w - 2, w - 1):
            dst[x] = (
                _K0 * (np.int32(src[_reflect(x - 2, w)]) + np.int32(src[_reflect(x + 2, w)]))
                + _K1 * (np.int32(src[_reflect(x - 1, w)]) + np.int32(src[_reflect(x + 1, w)]))
                + _K2 * np.int32(src[x])
            )
    # eight partial histograms: a smooth image repeats levels along a row, and one counter
    # incremented back to back stalls on its own store
    hist = np.zeros((8, 256), dtype=np.int32)
    for y in range(h):
        r_2 = rows[_reflect(y - 2, h)]
        r_1 = rows[_reflect(y - 1, h)]
        r0 = rows[y]
        r1 = rows[_reflect(y + 1, h)]
        r2 = rows[_reflect(y + 2, h)]
        dst8 = out[y]
        for x in range(w):
            dst8[x] = (
                _K0 * (np.int32(r_2[x]) + np.int32(r2[x]))
                + _K1 * (np.int32(r_1[x]) + np.int32(r1[x]))
                + _K2 * np.int32(r0[x])
                + _HALF
            ) >> np.int32(16)
        x = 0
        while x + 8 <= w:
            hist[0, dst8[x]] += 1
            hist[1, dst8[x + 1]] += 1
            hist[2, dst8[x + 2]] += 1
            hist[3, dst8[x + 3]] += 1
            hist[4, dst8[x + 4]] += 1
            hist[5, dst8[x + 5]] += 1
            hist[6, dst8[x + 6]] += 1
            hist[7, dst8[x + 7]] += 1
            x += 8
        while x < w:
            hist[0, dst8[x]] += 1
            x += 1
    counts = np.zeros(256, dtype=np.int64)
    for k in range(8):
        for i in range(256):
            counts[i] += hist[k, i]
    thresh = _otsu(counts, h * w)
    level = np.uint8(thresh)
    for y in range(h):
        dst8 = out[y]
        for x in range(w):
            dst8[x] = 255 if dst8[x] > level else 0
    return thresh
