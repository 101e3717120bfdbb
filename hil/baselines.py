"""Baselines the bench scores on the same frames (or the same scenario) as dffd.

* **known-size pinhole** ``z = f R / r``: needs the real size R, which dffd does not have; on
  dffd's own tracked ``r`` it is the bound of what size alone gives.
* **ArUco marker pose**: what a user would pick if a marker could be stuck on the target —
  ``cv2.aruco.ArucoDetector`` + ``cv2.solvePnP`` (IPPE_SQUARE) with the pinhole intrinsics of the
  lens table; depth is the marker centre's z in the camera frame.
* **full focus sweep** (classic depth from focus): step the focus through the whole range, one
  clean frame per setting, take the sharpest (Tenengrad over a window on the target), refine by a
  parabola through ln(sharpness) of the peak and its neighbours, and map the setting to depth
  through the lens table. Its rate is one depth per sweep.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.lens import Lens

Gray = npt.NDArray[np.uint8]

# A blob for the sweep's target window: pixels this far above the background level (fraction of
# the frame's peak contrast). Half-maximum keeps the centroid of a defocused disc where it is.
BLOB_LEVEL = 0.5
# Minimum blob area (px²) so noise specks are never taken for the target.
MIN_BLOB_AREA_PX = 12.0


def known_size_depth(r_px: float, size_m: float, focal_length_mm: float, pitch_mm: float) -> float:
    """Pinhole ranging (3): ``z = f R / r`` with ``f`` in pixels."""
    if r_px <= 0:
        return math.nan
    return focal_length_mm / pitch_mm * size_m / r_px


def square_side_for_size(size_m: float) -> float:
    """Side of a square whose boundary has ``sqrt(tr Σ) = size_m``.

    Points uniform along a square's perimeter of side s: var x = (s²/4 + s²/12)/2 = s²/6 per axis,
    so tr Σ = s²/3 and s = √3 R.
    """
    return math.sqrt(3.0) * size_m


@dataclass
class ArucoBaseline:
    """Marker detection + PnP on one frame."""

    marker_side_m: float
    focal_length_px: float
    frame_size: tuple[int, int]
    dictionary: str = "DICT_4X4_50"
    marker_id: int | None = None

    def __post_init__(self) -> None:
        dict_id = getattr(cv2.aruco, self.dictionary, None)
        if dict_id is None:
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50)")
        params = cv2.aruco.DetectorParameters()
        # Corner refinement: the marker's corners on a slightly blurred image. The contour of the
        # adaptive threshold (mean − C) lies inside the dark square, and the gradient-based
        # SUBPIX refinement moves a blurred convex corner inward too: the marker looks ~1 px
        # smaller, a depth bias that grows ∝ z (static ArUco pass, reference optics, 5 s a
        # depth at 1.5/2/4 m: NONE +0.69/+0.66/+0.70 %, SUBPIX +0.45/+0.34/+1.11 %, CONTOUR
        # +1.2/+0.8/+2.1 %). The AprilTag refinement fits the edges: +0.56/+0.11/+0.10 %
        # (std 2.7 mm at 4 m). docs/estimation.md §10.
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
        self._detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dict_id), params)
        w, h = self.frame_size
        f = self.focal_length_px
        self._k = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        half = self.marker_side_m / 2.0
        # IPPE_SQUARE's required corner order: top-left, top-right, bottom-right, bottom-left.
        self._obj = np.array(
            [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]],
            dtype=np.float64,
        )
        self.detections = 0
        self.misses = 0

    def depth(self, image: npt.NDArray[np.uint8]) -> float | None:
        """Depth (m) of the marker centre, or None when no marker is found."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            self.misses += 1
            return None
        pick = 0
        if self.marker_id is not None:
            matches = [i for i, v in enumerate(ids.ravel()) if int(v) == self.marker_id]
            if not matches:
                self.misses += 1
                return None
            pick = matches[0]
        img_pts = np.asarray(corners[pick], dtype=np.float64).reshape(4, 2)
        ok, _rvec, tvec = cv2.solvePnP(
            self._obj, img_pts, self._k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        if not ok:
            self.misses += 1
            return None
        self.detections += 1
        return float(tvec[2, 0])


def find_blob(image: Gray) -> tuple[float, float, float] | None:
    """Centroid and equivalent radius (px) of the brightest-contrast blob, defocus-tolerant."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    small = cv2.GaussianBlur(gray, (0, 0), 2.0).astype(np.float32)
    bg = float(np.median(small))
    hi, lo = float(small.max()), float(small.min())
    # The target may be brighter or darker than the background: take the larger excursion.
    if hi - bg >= bg - lo:
        mask = small > bg + BLOB_LEVEL * (hi - bg)
    else:
        mask = small < bg - BLOB_LEVEL * (bg - lo)
    if max(hi - bg, bg - lo) < 10.0:
        return None
    n, _labels, stats, centroids = cv2.connectedComponentsWithStats(
        mask.astype(np.uint8), connectivity=8
    )
    if n <= 1:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    best = int(np.argmax(areas)) + 1
    area = float(stats[best, cv2.CC_STAT_AREA])
    if area < MIN_BLOB_AREA_PX:
        return None
    cx, cy = centroids[best]
    return float(cx), float(cy), math.sqrt(area / math.pi)


def tenengrad(image: Gray, center: tuple[float, float], half: int) -> float:
    """Sum of squared Sobel gradient over a (2·half+1)² window at ``center`` (clipped)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    cx, cy = round(center[0]), round(center[1])
    x0, x1 = max(cx - half, 0), min(cx + half + 1, w)
    y0, y1 = max(cy - half, 0), min(cy + half + 1, h)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return 0.0
    patch = gray[y0:y1, x0:x1].astype(np.float32)
    gx = cv2.Sobel(patch, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(patch, cv2.CV_32F, 0, 1, ksize=3)
    return float(np.sum(gx * gx + gy * gy))


def sweep_depth(counts: Sequence[int], sharpness: Sequence[float], lens: Lens) -> float | None:
    """Depth from a focus sweep: sharpest setting refined by a parabola through ln(sharpness)."""
    if len(counts) < 3 or len(counts) != len(sharpness):
        return None
    order = np.argsort(np.asarray(counts))
    c = np.asarray(counts, dtype=np.float64)[order]
    s = np.asarray(sharpness, dtype=np.float64)[order]
    if not np.all(s > 0):
        return None
    v = lens.v_from_counts_array(c)
    i = int(np.argmax(s))
    if i == 0 or i == len(s) - 1:
        v_best = float(v[i])  # peak at an end of the range: no refinement possible
    else:
        x = v[i - 1 : i + 2]
        y = np.log(s[i - 1 : i + 2])
        a2, a1, _ = np.polyfit(x - x[1], y, 2)
        v_best = float(x[1] - a1 / (2 * a2)) if a2 < 0 else float(x[1])
        v_best = min(max(v_best, float(x[0])), float(x[2]))
    if v_best <= lens.focal_length_mm:
        return None
    return lens.depth_from_v(v_best)
