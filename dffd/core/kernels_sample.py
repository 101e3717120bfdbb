"""Compiled kernels of the samples along a contour's normals (numba, ``nogil``).

The contour's outward normals and box (:func:`normals_and_box`), the gradient window's bilinear
samples along every normal (:func:`sample_normals`) and one bilinear sample of an 8-bit image
(:func:`sample_u8`, for :func:`dffd.core.kernels.polarity`): each the value of OpenCV 5's
``remap`` (float32 coordinates, ``p00 + a (p01 − p00)`` with fused multiply-adds). Split from
:mod:`dffd.core.kernels`, which re-exports normals_and_box and sample_normals and calls them in
``fit_passes``; their NumPy twins are :mod:`dffd.core.kernels_numpy`'s. This module imports
nothing of the fit (no import cycle); numba compiles these kernels into their callers there
(see :func:`dffd.core.kernel_jit.jit` on what that means for the cache).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_jit import jit as _jit

__all__ = ["normals_and_box", "sample_normals", "sample_u8"]

FloatArray = npt.NDArray[np.float64]

# numba types of the kernels' arrays (all C-contiguous)
_M, _M32 = "float64[:, ::1]", "float32[:, ::1]"
# sample coordinates beyond this (or NaN) are outside any window: no integer conversion
_HUGE = 1e9


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


@_jit("float32(float32, float32, float32, float32, float32, float32)", contract=True)
def _lerp2(  # noqa: PLR0917 - numba kernels take positional arguments
    p00: np.float32, p01: np.float32, p10: np.float32, p11: np.float32, a: np.float32, b: np.float32
) -> np.float32:
    """Bilinear interpolation as OpenCV 5's remap: ``p00 + a (p01 − p00)`` per row, then
    between the rows, in float32, each a fused multiply-add where the CPU has one (its SIMD
    path's ``v_fma``; compiled with ``contract``)."""
    top = a * (p01 - p00) + p00
    bot = a * (p11 - p10) + p10
    return b * (bot - top) + top


@_jit(f"float32({_M32}, int64, int64, float32, float32, int64, int64)")
def _bilinear(  # noqa: PLR0917 - numba kernels take positional arguments
    g: npt.NDArray[np.float32], ix: int, iy: int, a: np.float32, b: np.float32, w: int, h: int
) -> np.float32:
    """One bilinear sample at a window's border: pixels outside ``g`` count as 0."""
    zero = np.float32(0.0)
    in_x0 = 0 <= ix < w
    in_x1 = 0 <= ix + 1 < w
    p00 = p01 = p10 = p11 = zero
    if 0 <= iy < h:
        p00 = g[iy, ix] if in_x0 else zero
        p01 = g[iy, ix + 1] if in_x1 else zero
    if 0 <= iy + 1 < h:
        p10 = g[iy + 1, ix] if in_x0 else zero
        p11 = g[iy + 1, ix + 1] if in_x1 else zero
    return _lerp2(p00, p01, p10, p11, a, b)


@_jit(f"void({_M32}, {_M32}, float64, float64, {_M}, {_M}, int64, {_M32}, {_M32})")
def sample_normals(  # noqa: PLR0917 - numba kernels take positional arguments
    gx: npt.NDArray[np.float32],
    gy: npt.NDArray[np.float32],
    x0: float,
    y0: float,
    pts: FloatArray,
    normals: FloatArray,
    s: int,
    bx: npt.NDArray[np.float32],
    by: npt.NDArray[np.float32],
) -> None:
    """Bilinear samples of the gradient window (corner ``x0``, ``y0`` in the frame) along every
    normal, −s … s px, into ``bx``, ``by``; 0 outside the window.

    The same values as ``cv2.remap(g, mapx, mapy, INTER_LINEAR)`` on float32 maps (OpenCV 5:
    exact float coordinates, ``p00 + a (p01 − p00)`` with fused multiply-adds: _lerp2), which
    it replaced.
    """
    h, w = gx.shape
    for i in range(pts.shape[0]):
        for j in range(2 * s + 1):
            step = float(j - s)
            mx = np.float32(pts[i, 0] + step * normals[i, 0] - x0)
            my = np.float32(pts[i, 1] + step * normals[i, 1] - y0)
            if 0 <= mx < w - 1 and 0 <= my < h - 1:  # all four pixels inside: the common case
                ix = int(mx)
                iy = int(my)
                a = mx - np.float32(ix)  # exact: float32 less its integer part
                b = my - np.float32(iy)
                bx[i, j] = _lerp2(
                    gx[iy, ix], gx[iy, ix + 1], gx[iy + 1, ix], gx[iy + 1, ix + 1], a, b
                )
                by[i, j] = _lerp2(
                    gy[iy, ix], gy[iy, ix + 1], gy[iy + 1, ix], gy[iy + 1, ix + 1], a, b
                )
            elif abs(mx) < _HUGE and abs(my) < _HUGE:
                ix = math.floor(mx)
                iy = math.floor(my)
                a = mx - np.float32(ix)
                b = my - np.float32(iy)
                bx[i, j] = _bilinear(gx, ix, iy, a, b, w, h)
                by[i, j] = _bilinear(gy, ix, iy, a, b, w, h)
            else:  # NaN or far outside
                bx[i, j] = np.float32(0.0)
                by[i, j] = np.float32(0.0)


@_jit("float32(uint8[:, ::1], float64, float64, int64, int64)")
def sample_u8(gray: npt.NDArray[np.uint8], x: float, y: float, w: int, h: int) -> np.float32:
    """One bilinear sample of ``gray`` at float32(x, y), border replicated (NaN: 0)."""
    mx = np.float32(x)
    my = np.float32(y)
    if not (abs(mx) < _HUGE and abs(my) < _HUGE):
        return np.float32(0.0)
    ix = math.floor(mx)
    iy = math.floor(my)
    a = mx - np.float32(ix)
    b = my - np.float32(iy)
    x0 = min(max(ix, 0), w - 1)
    x1 = min(max(ix + 1, 0), w - 1)
    y0 = min(max(iy, 0), h - 1)
    y1 = min(max(iy + 1, 0), h - 1)
    return _lerp2(
        np.float32(gray[y0, x0]), np.float32(gray[y0, x1]), np.float32(gray[y1, x0]),
        np.float32(gray[y1, x1]), a, b,
    )  # fmt: skip
