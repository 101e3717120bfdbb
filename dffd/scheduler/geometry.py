"""Angles of image points, and the VISCA pan/tilt speed table the head is commanded in."""

from __future__ import annotations

import math

# Pan/tilt speed table for VISCA speed indices 01…18 (deg/s), EVI-D100 reference model.
VISCA_SPEEDS_DEG_S: tuple[float, ...] = (
    2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0,
    27.0, 34.0, 42.0, 52.0, 65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0,
)  # fmt: skip
PAN_MAX_SPEED_INDEX = 0x18
TILT_MAX_SPEED_INDEX = 0x14


def pixel_offset_to_deg(offset_px: float, focal_length_mm: float, pixel_pitch_mm: float) -> float:
    """Angle (deg) off the optical axis of an image point ``offset_px`` from the centre."""
    return math.degrees(math.atan2(offset_px * pixel_pitch_mm, focal_length_mm))


def visca_speed_index(rate_deg_s: float, max_index: int) -> int:
    """Signed VISCA speed index whose table speed is nearest (log scale) to ``rate_deg_s``.

    Returns 0 only for a zero rate: any non-zero rate maps to at least index 1 (speed 00 is a
    syntax error on some models, docs/design.md §6).
    """
    if rate_deg_s == 0.0 or not math.isfinite(rate_deg_s):
        return 0
    magnitude = abs(rate_deg_s)
    table = VISCA_SPEEDS_DEG_S[:max_index]
    best = min(range(len(table)), key=lambda i: abs(math.log(table[i] / magnitude)))
    return int(math.copysign(best + 1, rate_deg_s))


def speed_of_index(index: int) -> float:
    """Signed deg/s of a signed VISCA speed index (0 → 0)."""
    if index == 0:
        return 0.0
    return math.copysign(VISCA_SPEEDS_DEG_S[abs(index) - 1], index)


def nearest_speed_index(rate_deg_s: float, max_index: int) -> int:
    """Signed VISCA speed index nearest to ``rate_deg_s``, 0 (stopped) included: rates below half
    the slowest speed map to 0, others as :func:`visca_speed_index`."""
    if abs(rate_deg_s) < VISCA_SPEEDS_DEG_S[0] / 2.0:
        return 0
    return visca_speed_index(rate_deg_s, max_index)


def step_index(index: int, direction: int, max_index: int) -> int:
    """The signed speed index one code from ``index`` in ``direction`` (through 0)."""
    stepped = index + direction
    return max(-max_index, min(max_index, stepped))
