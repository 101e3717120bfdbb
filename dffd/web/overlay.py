"""Draw what the estimator sees on a frame and encode it as JPEG (runs in a worker thread).

Pure functions of a :class:`~dffd.web.interface.FrameView`: the contour and its search normals,
the centroid, the acquisition box, and on the right edge the focus bracket (the burst settings
and the current setting on a bar spanning the lens's focus range).
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

from dffd.web.interface import FrameView, Overlay

# JPEG quality: 75 keeps a 640×480 frame near 30–40 kB, sharp enough to judge the contour.
JPEG_QUALITY: Final = 75
# Frames wider than this are halved (or more) before drawing: a browser panel needs no more.
MAX_WIDTH_PX: Final = 960

_SHIFT: Final = 4  # sub-pixel bits for cv2 drawing
_SCALE: Final = 1 << _SHIFT
# BGR colours
_CONTOUR: Final = (0, 220, 255)
_NORMAL: Final = (80, 200, 80)
_CENTROID: Final = (60, 60, 255)
_ROI: Final = (255, 200, 0)
_BRACKET: Final = (0, 160, 255)
_FOCUS: Final = (255, 255, 255)
_TEXT: Final = (255, 255, 255)
_BAR_W: Final = 10
_BAR_MARGIN: Final = 16


def annotate(view: FrameView, max_width: int = MAX_WIDTH_PX) -> npt.NDArray[np.uint8]:
    """A BGR copy of the frame (downscaled to ``max_width``) with the overlay drawn on it."""
    image: npt.NDArray[np.uint8] = view.image
    scale = 1.0
    if image.shape[1] > max_width:
        scale = max_width / image.shape[1]
        image = np.asarray(
            cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), np.uint8
        )
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    out = np.asarray(out, dtype=np.uint8)
    _draw(out, view.overlay, scale)
    return out


def encode_jpeg(view: FrameView, quality: int = JPEG_QUALITY) -> bytes:
    """The annotated frame as JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", annotate(view), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"JPEG encoding failed for frame {view.index}")
    return bytes(buf)


def normals(points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Unit normals of a closed polyline at its vertices (central differences)."""
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    n = np.stack((tangent[:, 1], -tangent[:, 0]), axis=1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.asarray(n / np.where(length > 0, length, 1.0), dtype=np.float64)


def _fixed(points: npt.NDArray[np.float64]) -> npt.NDArray[np.int32]:
    return np.asarray(np.rint(points * _SCALE), dtype=np.int32)


def _draw(img: npt.NDArray[np.uint8], ov: Overlay, scale: float) -> None:
    h, w = img.shape[:2]
    if ov.roi is not None:
        x, y, rw, rh = (round(v * scale) for v in ov.roi)
        cv2.rectangle(img, (x, y), (x + rw, y + rh), _ROI, 1, cv2.LINE_AA)
    pts = ov.contour_px
    if pts is not None and len(pts) >= 3 and np.all(np.isfinite(pts)):
        p = np.asarray(pts, dtype=np.float64) * scale
        if ov.normal_half_px > 0:
            d = normals(p) * ov.normal_half_px * scale
            segments = np.stack((p - d, p + d), axis=1)
            cv2.polylines(
                img,
                list(_fixed(segments)),
                isClosed=False,
                color=_NORMAL,
                thickness=1,
                lineType=cv2.LINE_AA,
                shift=_SHIFT,
            )
        cv2.polylines(
            img,
            [_fixed(p)],
            isClosed=True,
            color=_CONTOUR,
            thickness=1,
            lineType=cv2.LINE_AA,
            shift=_SHIFT,
        )
    if ov.centroid_px is not None and all(np.isfinite(ov.centroid_px)):
        cx, cy = (round(v * scale) for v in ov.centroid_px)
        cv2.drawMarker(img, (cx, cy), _CENTROID, cv2.MARKER_CROSS, 14, 2, cv2.LINE_AA)
    _draw_bracket(img, ov, w, h)
    label = ov.state
    if ov.z_m is not None:
        label += f"  z {ov.z_m:.3f} m"
        if ov.sigma_m is not None:
            label += f" ± {ov.sigma_m:.3f}".replace("±", "+/-")
    # on a dark box, not over a thicker black copy: Hershey glyphs advance by their stroke's
    # thickness, so a thick outline drifts off the thin text as the label goes on
    (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 1)
    cv2.rectangle(img, (4, 20 - th - 4), (12 + tw, 20 + base + 2), (0, 0, 0), -1)
    cv2.putText(img, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, _TEXT, 1, cv2.LINE_AA)


def _draw_bracket(img: npt.NDArray[np.uint8], ov: Overlay, w: int, h: int) -> None:
    if ov.counts_range is None:
        return
    lo, hi = ov.counts_range
    if hi <= lo:
        return
    x0 = w - _BAR_MARGIN - _BAR_W
    top, bottom = _BAR_MARGIN, h - _BAR_MARGIN

    def y_of(counts: int) -> int:
        f = min(1.0, max(0.0, (counts - lo) / (hi - lo)))
        return round(bottom - f * (bottom - top))  # near focus (high counts) at the top

    cv2.rectangle(img, (x0, top), (x0 + _BAR_W, bottom), (90, 90, 90), 1)
    if ov.bracket_counts:
        ys = [y_of(c) for c in ov.bracket_counts]
        cv2.rectangle(img, (x0, min(ys)), (x0 + _BAR_W, max(ys)), _BRACKET, -1)
        for y in ys:
            cv2.line(img, (x0 - 4, y), (x0 + _BAR_W + 4, y), _BRACKET, 1)
    if ov.focus_counts is not None:
        y = y_of(ov.focus_counts)
        tri = np.array([[x0 - 2, y], [x0 - 10, y - 5], [x0 - 10, y + 5]], dtype=np.int32)
        cv2.fillConvexPoly(img, tri, _FOCUS, cv2.LINE_AA)
