"""A target cut by the frame's edge: where to look while nothing whole is in view.

:func:`dffd.core.contour.find_target` takes only blobs that lie wholly inside the frame (a
contour cut by the edge cannot be followed). A target that starts half out of view and moves
away is then never acquired: nothing is tracked, so pan/tilt never turns towards it
(``random``'s seed 2 on the bench: the disc starts cut by the bottom edge, leaves the view
within a second and comes back 15 s later). :func:`find_clipped_target` finds such a blob —
convex, target-sized, touching the frame's edge — and gives the centroid of its visible part,
which lies on the target's side of the frame: the pipeline reports it while acquiring
(``PipelineOutput.candidate_px``) and the head turns that way until the whole target is in view.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

# A visible part this convex (area over its convex hull's) is taken for a cut-off target: a disc
# or a card cut by a straight edge stays convex (1.0 up to the pixel outline), while the
# background's threshold regions that reach the edge are ragged.
MIN_SOLIDITY = 0.92
# Its visible area at least this fraction of the disc it would be at the tracker's smallest
# radius (half a target must show), and at most this fraction of the frame (not the background).
MIN_AREA_FRACTION = 0.5
MAX_FRAME_FRACTION = 0.25


def find_clipped_target(
    gray: npt.NDArray[np.uint8], min_radius_px: float = 6.0
) -> tuple[float, float] | None:
    """The visible centroid (x, y) of the most salient convex blob cut by the frame's edge, or
    None (both polarities of an Otsu threshold, as ``find_target``)."""
    h, w = gray.shape[:2]
    patch = cv2.GaussianBlur(gray, (5, 5), 1.0)
    _, binary = cv2.threshold(patch, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    least = MIN_AREA_FRACTION * math.pi * min_radius_px**2
    most = MAX_FRAME_FRACTION * w * h
    best: tuple[float, tuple[float, float]] | None = None
    for mask in (binary, cv2.bitwise_not(binary)):
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for raw in contours:
            cnt = np.asarray(raw, dtype=np.int32)
            bx, by, bw, bh = cv2.boundingRect(cnt)
            if not (bx <= 0 or by <= 0 or bx + bw >= w or by + bh >= h):
                continue  # wholly inside: find_target's
            area = float(cv2.contourArea(cnt))
            if not least <= area <= most:
                continue
            hull = float(cv2.contourArea(cv2.convexHull(cnt)))
            solidity = area / hull if hull > 0 else 0.0
            if solidity < MIN_SOLIDITY:
                continue
            m = cv2.moments(cnt)
            centroid = (m["m10"] / m["m00"], m["m01"] / m["m00"])
            score = area * solidity
            if best is None or score > best[0]:
                best = (score, (float(centroid[0]), float(centroid[1])))
    return None if best is None else best[1]


__all__ = ["find_clipped_target"]
