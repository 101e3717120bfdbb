"""Angles of image points, and VISCA pan/tilt speed codes on a camera's speed table.

A speed table lists the deg/s of speed codes 01, 02, …; the camera model's tables come from the
driver's profile (``drivers.visca.camera.CameraProfile``) through ``SchedulerConfig``.
"""

from __future__ import annotations

import math


def pixel_offset_to_deg(offset_px: float, focal_length_mm: float, pixel_pitch_mm: float) -> float:
    """Angle (deg) off the optical axis of an image point ``offset_px`` from the centre."""
    return math.degrees(math.atan2(offset_px * pixel_pitch_mm, focal_length_mm))


def visca_speed_index(rate_deg_s: float, table: tuple[float, ...]) -> int:
    """Signed VISCA speed index whose speed on ``table`` is nearest (log scale) to ``rate_deg_s``.

    Returns 0 only for a zero rate: any non-zero rate maps to at least index 1 (speed 00 is a
    syntax error on some models, docs/design.md §6).
    """
    if rate_deg_s == 0.0 or not math.isfinite(rate_deg_s):
        return 0
    magnitude = abs(rate_deg_s)
    best = min(range(len(table)), key=lambda i: abs(math.log(table[i] / magnitude)))
    return int(math.copysign(best + 1, rate_deg_s))


def speed_of_index(index: int, table: tuple[float, ...]) -> float:
    """Signed deg/s of a signed VISCA speed index on ``table`` (0 → 0)."""
    if index == 0:
        return 0.0
    return math.copysign(table[abs(index) - 1], index)


def nearest_speed_index(rate_deg_s: float, table: tuple[float, ...]) -> int:
    """Signed VISCA speed index nearest to ``rate_deg_s``, 0 (stopped) included: rates below half
    the slowest speed map to 0, others as :func:`visca_speed_index`."""
    if abs(rate_deg_s) < table[0] / 2.0:
        return 0
    return visca_speed_index(rate_deg_s, table)


def step_index(index: int, direction: int, max_index: int) -> int:
    """The signed speed index one code from ``index`` in ``direction`` (through 0)."""
    stepped = index + direction
    return max(-max_index, min(max_index, stepped))
