"""What the scheduler asks of the camera: focus and pan/tilt actions, executed by the shell.

The shell reports each one's outcome back through the matching ``Scheduler.on_…`` event.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FocusMove:
    """Focus Direct to ``counts``; report Completion with ``on_focus_completed(move_id, t)``."""

    move_id: int
    counts: int


@dataclass(frozen=True, slots=True)
class FocusInquiry:
    """FocusPosInq; report the reply with ``on_focus_position(t, counts)``."""


@dataclass(frozen=True, slots=True)
class PanTiltDrive:
    """Pan-tiltDrive: signed VISCA speed indices (0 = stop that axis) and their rates in deg/s."""

    pan_speed: int
    tilt_speed: int
    pan_rate_deg_s: float
    tilt_rate_deg_s: float


@dataclass(frozen=True, slots=True)
class PanTiltAbsolute:
    """Absolute pan/tilt move (degrees) at VISCA speed indices."""

    pan_deg: float
    tilt_deg: float
    pan_speed: int
    tilt_speed: int


@dataclass(frozen=True, slots=True)
class PanTiltStop:
    """Stop both pan/tilt axes."""


@dataclass(frozen=True, slots=True)
class PanTiltInquiry:
    """Pan-tiltPosInq; report with ``on_pan_tilt_position(t, pan_deg, tilt_deg)``."""


Action = FocusMove | FocusInquiry | PanTiltDrive | PanTiltAbsolute | PanTiltStop | PanTiltInquiry
PAN_TILT_ACTIONS = (PanTiltDrive, PanTiltAbsolute, PanTiltStop, PanTiltInquiry)
