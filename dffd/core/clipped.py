"""A target cut by the frame's edge: where to look while nothing whole is in view.

:func:`dffd.core.acquisition.find_target` takes only blobs that lie wholly inside the frame (a
contour cut by the edge cannot be followed). A target that starts half out of view and moves
away is then never acquired: nothing is tracked, so pan/tilt never turns towards it
(``random``'s seed 2 on the bench: the disc starts cut by the bottom edge, leaves the view
within a second and comes back 15 s later). :func:`find_clipped_blobs` finds such blobs —
convex, target-sized, touching the frame's edge — with the centroid of their visible part,
which lies on the blob's side of the frame.

Convexity at the edge is not proof of a target: a textured background thresholded by Otsu breaks
into blobs, and a few small ones that reach the edge are convex too (the aberrated optics' wall:
14×11 px caps every few frames). Chasing each of them in turn spins the head away from where
the target is (``stop-and-go`` on that wall was never acquired). Two defences. A blob must stand
out of the background around it (:data:`MIN_EDGE_CONTRAST`): a threshold region of a texture
does not. And :class:`ClippedHint` *tests* what passes (a speck on the wall is high-contrast,
but no target): it turns towards one blob at a time, in pan/tilt directions (a blob of the
scene stays where it is while the head turns; a new blob is a new direction), and the blob must
then come into view **whole** — a closed, convex, target-sized contour that the acquisition
takes. A blob whose direction is in full view without an acquisition, or that is not reached
within :data:`TRY_TIMEOUT_S`, is rejected: its direction is remembered and never chased again.
After :data:`MAX_TRIES` rejected blobs the hint gives up, the core reports no centroid, and the
scheduler's search sweep (``dffd/scheduler/search.py``) takes over after ``search_after_s``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

__all__ = [
    "MAX_TRIES",
    "MIN_EDGE_CONTRAST",
    "TRY_TIMEOUT_S",
    "VERIFY_FRAMES",
    "ClippedBlob",
    "ClippedHint",
    "find_clipped_blobs",
    "find_clipped_target",
]

logger = logging.getLogger(__name__)

# A visible part this convex (area over its convex hull's) is taken for a cut-off target: a disc
# or a card cut by a straight edge stays convex (1.0 up to the pixel outline), while the
# background's threshold regions that reach the edge are ragged.
MIN_SOLIDITY = 0.92
# Its visible area at least this fraction of the disc it would be at the tracker's smallest
# radius (half a target must show), and at most this fraction of the frame (not the background).
MIN_AREA_FRACTION = 0.5
MAX_FRAME_FRACTION = 0.25
# Its edge must stand out of the background around it: the visible part's mean differs from the
# mean of a ring just outside it (RING_GAP_PX to RING_OUTER_PX away, clear of a few pixels of
# blur) by at least this many robust standard deviations (1.4826 MAD) of that ring. A threshold
# region of a textured background is where the texture happens to lie above Otsu's level: it
# differs from its own surroundings by a few spreads at most (the peaks of a Gaussian texture;
# six spreads it would reach about once in 10⁹ samples); a target is another surface. Measured
# (not fitted): the aberrated optics' wall caps 0.7-1.4, a synthetic Gaussian texture's 0.6-3.7
# (tests/test_core_clipped_hint.py), the cut-off disc of ``random`` seed 2 20-33 on both optics.
MIN_EDGE_CONTRAST = 6.0
RING_GAP_PX = 4
RING_OUTER_PX = 12

# Blobs chased before the hint gives up for good (until the next acquire or release). Each try
# costs one turn of the head (at most half a field of view) and a few frames to look: three
# keep the time lost to a background's false blobs to a few seconds before the search sweep.
MAX_TRIES = 3
# A try that has not brought its blob into view whole by then is rejected. The blob's visible
# centroid is at most half a field of view off the axis; the head's drive speeds turn that far
# in well under a second (EVI-D100: 3.6° at 14-27°/s), so two seconds bound a try that the
# head cannot finish (a blob beyond the pan/tilt range, a head that does not move).
TRY_TIMEOUT_S = 2.0
# Frames in which the blob's direction lies in full view while the acquisition (which searches
# the whole frame on every frame before a first sighting) takes nothing: then the blob is not a
# target. More than one: a frame exposed while the head turns or the focus moves is smeared.
VERIFY_FRAMES = 5


@dataclass(frozen=True, slots=True)
class ClippedBlob:
    """A convex blob cut by the frame's edge: its visible part's centroid and size."""

    centroid_px: tuple[float, float]
    extent_px: float  # the visible part's larger bounding-box side
    score: float  # area × solidity: the most salient first


def find_clipped_blobs(
    gray: npt.NDArray[np.uint8], min_radius_px: float = 6.0
) -> list[ClippedBlob]:
    """The convex, target-sized blobs cut by the frame's edge, most salient first (both
    polarities of an Otsu threshold, as ``find_target``)."""
    h, w = gray.shape[:2]
    patch = cv2.GaussianBlur(gray, (5, 5), 1.0)
    _, binary = cv2.threshold(patch, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    least = MIN_AREA_FRACTION * math.pi * min_radius_px**2
    most = MAX_FRAME_FRACTION * w * h
    found: list[ClippedBlob] = []
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
            if _edge_contrast(gray, cnt, (bx, by, bw, bh)) < MIN_EDGE_CONTRAST:
                continue  # no more than the background's own texture
            m = cv2.moments(cnt)
            centroid = (float(m["m10"] / m["m00"]), float(m["m01"] / m["m00"]))
            found.append(ClippedBlob(centroid, float(max(bw, bh)), area * solidity))
    found.sort(key=lambda b: b.score, reverse=True)
    return found


def find_clipped_target(
    gray: npt.NDArray[np.uint8], min_radius_px: float = 6.0
) -> tuple[float, float] | None:
    """The visible centroid (x, y) of the most salient convex blob cut by the frame's edge, or
    None."""
    blobs = find_clipped_blobs(gray, min_radius_px)
    return blobs[0].centroid_px if blobs else None


class ClippedHint:
    """Where the head should turn while acquiring: one cut-off blob at a time, each verified.

    Pure: fed the whole frame searched by the acquisition, its exposure time and the head's
    pan/tilt during the exposure (the frame's tag); ``focal_px`` = focal length / pixel pitch.
    """

    def __init__(
        self,
        focal_px: float,
        *,
        max_tries: int = MAX_TRIES,
        try_timeout_s: float = TRY_TIMEOUT_S,
        verify_frames: int = VERIFY_FRAMES,
    ) -> None:
        if not focal_px > 0:
            raise ValueError(f"focal_px must be > 0, got {focal_px}")
        self.focal_px = focal_px
        self.max_tries = max_tries
        self.try_timeout_s = try_timeout_s
        self.verify_frames = verify_frames
        self.reset()

    def reset(self) -> None:
        """Forget every try and rejection (a new acquisition)."""
        self.tries = 0
        self.rejected: list[tuple[float, float, float]] = []  # pan, tilt, radius (deg)
        self._chase: _Chase | None = None

    @property
    def gave_up(self) -> bool:
        """Every try was rejected: the hint reports nothing more (the search sweep's turn)."""
        return self._chase is None and self.tries >= self.max_tries

    def update(
        self,
        gray: npt.NDArray[np.uint8],
        t: float,
        pan_deg: float,
        tilt_deg: float,
        min_radius_px: float = 6.0,
    ) -> tuple[float, float] | None:
        """The image point to turn to on this frame (the chased blob's visible centroid), or
        None; call it on frames on which the whole-frame acquisition found nothing."""
        if self.gave_up:
            return None
        h, w = gray.shape[:2]
        view = _View(self.focal_px, (w - 1) / 2.0, (h - 1) / 2.0, pan_deg, tilt_deg)
        blobs = find_clipped_blobs(gray, min_radius_px)
        chase = self._chase
        if chase is not None:
            blob = chase.match(blobs, view)
            if blob is not None:
                chase.follow(blob, view)
            elif view.inside(chase.direction, chase.extent_px, w, h):
                chase.whole_frames += 1  # in full view, and the acquisition took nothing
            if t - chase.started_at > self.try_timeout_s:
                self._reject(chase, "not in view whole before the try's timeout")
            elif chase.whole_frames >= self.verify_frames:
                self._reject(chase, "its direction in full view, and no target acquired there")
            else:
                return None if blob is None else blob.centroid_px
        if self.tries >= self.max_tries:
            return None
        for blob in blobs:
            direction = view.direction(blob.centroid_px)
            if not self._is_rejected(direction):
                self.tries += 1
                self._chase = _Chase(direction, blob.extent_px, t)
                return blob.centroid_px
        return None

    def _is_rejected(self, direction: tuple[float, float]) -> bool:
        return any(
            math.hypot(direction[0] - p, direction[1] - q) <= radius
            for p, q, radius in self.rejected
        )

    def _reject(self, chase: _Chase, why: str) -> None:
        radius = math.degrees(math.atan2(chase.extent_px, self.focal_px))
        self.rejected.append((chase.direction[0], chase.direction[1], radius))
        self._chase = None
        pan, tilt = chase.direction
        logger.info(
            "cut-off blob at pan %+.2f°, tilt %+.2f° rejected (%s): not a target",
            pan, tilt, why,
        )  # fmt: skip
        if self.tries >= self.max_tries:
            logger.info(
                "no cut-off blob came into view whole after %d tries: the hint gives up "
                "(the search sweep takes over)", self.tries,
            )  # fmt: skip


def _edge_contrast(
    gray: npt.NDArray[np.uint8], cnt: npt.NDArray[np.int32], box: tuple[int, int, int, int]
) -> float:
    """|mean inside − mean of the ring around| over the ring's robust spread (1.4826 MAD)."""
    h, w = gray.shape[:2]
    bx, by, bw, bh = box
    pad = RING_OUTER_PX + 1
    x0, y0 = max(bx - pad, 0), max(by - pad, 0)
    x1, y1 = min(bx + bw + pad, w), min(by + bh + pad, h)
    blob = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    cv2.drawContours(blob, [cnt - np.array([x0, y0], dtype=np.int32)], -1, 255, cv2.FILLED)
    near = np.asarray(cv2.dilate(blob, _disc(RING_GAP_PX)), dtype=np.uint8)
    outer = np.asarray(cv2.dilate(blob, _disc(RING_OUTER_PX)), dtype=np.uint8)
    ring = (outer > 0) & (near == 0)
    inner = np.asarray(cv2.erode(blob, _disc(1)), dtype=np.uint8)
    patch = gray[y0:y1, x0:x1]
    inside = patch[inner > 0].astype(np.float32)
    around = patch[ring].astype(np.float32)
    if inside.size < 5 or around.size < 5:
        return 0.0
    centre = float(np.median(around))
    spread = 1.4826 * float(np.median(np.abs(around - centre)))
    return abs(float(inside.mean()) - float(around.mean())) / max(spread, 1.0)


def _disc(radius: int) -> npt.NDArray[np.uint8]:
    return np.asarray(
        cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1)),
        dtype=np.uint8,
    )


@dataclass(frozen=True, slots=True)
class _View:
    """One frame's camera: image points ↔ pan/tilt directions (deg), the head's convention
    (image x to the right is positive pan, image y upwards positive tilt)."""

    focal_px: float
    cx: float
    cy: float
    pan_deg: float
    tilt_deg: float

    def direction(self, point: tuple[float, float]) -> tuple[float, float]:
        f = self.focal_px
        return (
            self.pan_deg + math.degrees(math.atan2(point[0] - self.cx, f)),
            self.tilt_deg + math.degrees(math.atan2(self.cy - point[1], f)),
        )

    def point(self, direction: tuple[float, float]) -> tuple[float, float] | None:
        """The image point of ``direction``, or None when it is 90° or more off the axis."""
        dp = math.radians(direction[0] - self.pan_deg)
        dt = math.radians(direction[1] - self.tilt_deg)
        if abs(dp) >= math.pi / 2 or abs(dt) >= math.pi / 2:
            return None
        return self.cx + self.focal_px * math.tan(dp), self.cy - self.focal_px * math.tan(dt)

    def inside(self, direction: tuple[float, float], margin_px: float, w: int, h: int) -> bool:
        """``direction`` is in view at least ``margin_px`` from every edge."""
        p = self.point(direction)
        return p is not None and (
            margin_px <= p[0] <= w - 1 - margin_px and margin_px <= p[1] <= h - 1 - margin_px
        )


@dataclass
class _Chase:
    """The blob being turned to: its last seen direction and size, since when, and for how many
    frames its direction was in full view without an acquisition."""

    direction: tuple[float, float]
    extent_px: float
    started_at: float
    whole_frames: int = 0

    def match(self, blobs: list[ClippedBlob], view: _View) -> ClippedBlob | None:
        """The blob of this frame that is this one (nearest direction, within its size)."""
        reach = math.degrees(math.atan2(self.extent_px, view.focal_px))
        best: tuple[float, ClippedBlob] | None = None
        for blob in blobs:
            d = view.direction(blob.centroid_px)
            off = math.hypot(d[0] - self.direction[0], d[1] - self.direction[1])
            if off <= reach and (best is None or off < best[0]):
                best = (off, blob)
        return None if best is None else best[1]

    def follow(self, blob: ClippedBlob, view: _View) -> None:
        """Seen again: the visible part grows as the head turns (and a target may move)."""
        self.direction = view.direction(blob.centroid_px)
        self.extent_px = max(self.extent_px, blob.extent_px)
