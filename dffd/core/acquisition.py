"""The acquisition search: the most salient closed blob of a frame or a region (docs/design.md
§5.4), the polygon :meth:`dffd.core.contour.ContourTracker.start` refines into a contour.

Split from :mod:`dffd.core.contour` (the tracker it starts); its mask is the compiled kernel of
:mod:`dffd.core.kernels_acquire`.
"""

from __future__ import annotations

import math
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core import kernel_dispatch
from dffd.core.contour import FloatArray

__all__ = ["find_target"]


def find_target(
    gray: npt.NDArray[np.uint8],
    roi: tuple[int, int, int, int] | None = None,
    min_radius_px: float = 6.0,
    *,
    downscale: int = 1,
) -> FloatArray | None:
    """The most salient closed high-contrast blob in ``roi`` (x, y, w, h) or the whole image.

    Otsu threshold of the smoothed region (both polarities; the dark one only where it can find a
    blob, see _polarities), external contours that do not touch the region border; score =
    area x circularity / (1 + distance to the region centre / size).
    Returns the boundary polygon in image coordinates, or None.

    ``downscale`` > 1 searches a ``downscale``× area-averaged copy of the region (the polygon is
    then scaled back onto ``gray``'s pixel centres): the cost falls with the area (~5× less on a
    whole 640×480 frame at 2) and the polygon is coarser by that factor, a start for
    :meth:`ContourTracker.start`, which refines it on ``gray``.
    """
    h, w = gray.shape[:2]
    if roi is None:
        x, y, rw, rh = 0, 0, w, h
    else:
        # the part of the ROI inside the frame (one partly or wholly outside is cut to it)
        x0, y0, x1, y1 = int(roi[0]), int(roi[1]), int(roi[0] + roi[2]), int(roi[1] + roi[3])
        x, y = max(x0, 0), max(y0, 0)
        rw, rh = min(x1, w) - x, min(y1, h) - y
    if rw < 8 or rh < 8:
        return None
    if downscale > 1:
        rw, rh = rw // downscale, rh // downscale
        if rw < 8 or rh < 8:
            return None
        min_radius_px /= downscale
    binary = _otsu_mask(gray, x, y, rw, rh, downscale)
    cx, cy = rw / 2.0, rh / 2.0
    best: tuple[float, npt.NDArray[np.int32]] | None = None
    min_area = math.pi * min_radius_px**2
    # A chain of n pixels (steps of at most √2) encloses at most (n√2)²/(4π) = n²/(2π) px²
    # (isoperimetric): shorter chains cannot reach min_area and are skipped uncomputed.
    min_points_sq = 2.0 * math.pi * min_area
    for mask in _polarities(binary):
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for raw in contours:
            cnt = cast("npt.NDArray[np.int32]", raw)  # (n, 1, 2) int32 chains, as they come
            n = len(cnt)
            if n * n < min_points_sq:
                continue
            bx, by, bw, bh = cv2.boundingRect(cnt)
            if bx <= 0 or by <= 0 or bx + bw >= rw or by + bh >= rh:
                continue  # touches the region border: background or a cut-off object
            area = float(cv2.contourArea(cnt))
            if area < min_area or area > 0.8 * rw * rh:
                continue
            perimeter = float(cv2.arcLength(cnt, closed=True))
            circularity = 4 * math.pi * area / max(perimeter**2, 1e-9)
            # the chain's mean: its integer sums are exact (NumPy's float mean is too), / n
            sx, sy = cnt.reshape(-1, 2).sum(axis=0, dtype=np.int64).tolist()
            dist = float(np.hypot(sx / n - cx, sy / n - cy))
            score = area * circularity / (1.0 + dist / math.sqrt(area))
            if best is None or score > best[0]:
                best = (score, cnt)
    if best is None:
        return None
    poly = best[1].reshape(-1, 2).astype(np.float64)
    if downscale > 1:
        # pixel i of the copy averages pixels d·i … d·i + d − 1: its centre is d·i + (d − 1)/2
        poly *= downscale
        poly += (downscale - 1) / 2.0
    if x or y:
        poly += np.array([x, y], dtype=np.float64)
    return poly


def _polarities(binary: npt.NDArray[np.uint8]) -> tuple[npt.NDArray[np.uint8], ...]:
    """The masks whose external contours find_target scores: ``binary`` (bright blobs) and, when
    a bright pixel lies on the region border, its inverse (dark blobs).

    findContours pads the image with 0, so the inverse's outside is a bright (255 in ``binary``)
    region: its external contours are the dark blobs that border the bright region joined to the
    outside. With no bright pixel on the border that region is the padding alone, and every dark
    blob it borders touches the border, which find_target rejects: the inverse's pass (~25 µs on
    a 320 × 240 mask, a quarter of the search) cannot find a candidate and is skipped. The
    result is the same as with both passes, bit for bit.
    """
    rh, rw = binary.shape
    # the first and last row, then the first and last column (strided views, no copies)
    if np.count_nonzero(binary[:: rh - 1]) or np.count_nonzero(binary[:, :: rw - 1]):
        return binary, cast("npt.NDArray[np.uint8]", cv2.bitwise_not(binary))
    return (binary,)


def _otsu_mask(  # noqa: PLR0917 - the region's corner, size and scale
    gray: npt.NDArray[np.uint8], x: int, y: int, rw: int, rh: int, downscale: int
) -> npt.NDArray[np.uint8]:
    """find_target's mask of the region (rw × rh after ``downscale``) at (x, y): Otsu's
    threshold of the region smoothed 5×5 (σ = 1), area-averaged first when downscaled.

    One kernel call (``acquire_mask``: OpenCV's values bit for bit, ~2× faster than its resize,
    blur and threshold) for a gray frame and a scale of 1 or 2, OpenCV's calls otherwise.
    """
    if gray.ndim == 2 and downscale in {1, 2} and gray.flags.c_contiguous:
        binary = np.empty((rh, rw), dtype=np.uint8)
        kernel_dispatch.current().acquire_mask(gray, x, y, downscale, binary)
        return binary
    region = gray[y : y + rh * downscale, x : x + rw * downscale]
    if downscale > 1:
        region = np.asarray(
            cv2.resize(region, (rw, rh), interpolation=cv2.INTER_AREA), dtype=np.uint8
        )
    patch = cv2.GaussianBlur(region, (5, 5), 1.0)
    _, mask = cv2.threshold(patch, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return np.asarray(mask, dtype=np.uint8)
