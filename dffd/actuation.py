"""The action executor's pure half: scheduler actions → VISCA requests, outcomes → scheduler.

The daemon's actuator tasks (over the asyncio VISCA link) and the lock-step bench (over the same
VISCA session against the simulated device, in virtual time) both translate with
:func:`request_for` and report with :func:`report_done` / :func:`report_failed`, so a camera
call means the same thing in every runner. Degrees and speed codes come from the driver's
:class:`~drivers.visca.camera.CameraProfile` of the configured model, never from the
simulator's constants (a shared constant would let a conversion bug cancel out).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeAlias

from dffd.scheduler import (
    Action,
    FocusInquiry,
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
)
from drivers.visca import codec_replies, codec_requests
from drivers.visca.camera import MOVE_TIMEOUT_FACTOR, CameraProfile, SpeedCode

if TYPE_CHECKING:
    from dffd.scheduler import Scheduler

__all__ = [
    "ActionRequest",
    "completion_timeout_s",
    "is_focus_action",
    "report_done",
    "report_failed",
    "request_for",
]

ActionRequest: TypeAlias = (
    codec_requests.FocusDirect
    | codec_requests.FocusPositionInquiry
    | codec_requests.PanTiltDrive
    | codec_requests.PanTiltAbsolute
    | codec_requests.PanTiltPositionInquiry
)


def is_focus_action(action: Action) -> bool:
    """True for the actions of the focus socket (the others are pan/tilt)."""
    return isinstance(action, FocusMove | FocusInquiry)


def request_for(action: Action, profile: CameraProfile) -> ActionRequest:
    """The VISCA request that executes ``action`` on a camera of ``profile``.

    ValueError when the action is outside the camera's ranges (the action then failed).
    """
    match action:
        case FocusMove(counts=counts):
            lo, hi = profile.focus_range
            if not lo <= counts <= hi:
                raise ValueError(f"focus counts {counts} outside {lo}..{hi} of the {profile.name}")
            return codec_requests.FocusDirect(counts)
        case FocusInquiry():
            return codec_requests.FocusPositionInquiry()
        case PanTiltDrive(pan_speed=pan, tilt_speed=tilt):
            # The scheduler's speed codes: its head model moves at those speeds. Speed 00 is a
            # syntax error on some models, so a stopped axis still carries code 01.
            pan_dir = codec_requests.PanDirection.STOP
            if pan:
                pan_dir = (
                    codec_requests.PanDirection.RIGHT
                    if pan > 0
                    else codec_requests.PanDirection.LEFT
                )
            tilt_dir = codec_requests.TiltDirection.STOP
            if tilt:
                tilt_dir = (
                    codec_requests.TiltDirection.UP
                    if tilt > 0
                    else codec_requests.TiltDirection.DOWN
                )
            return codec_requests.PanTiltDrive(
                profile.pan_speed_code(SpeedCode(max(1, abs(pan)))),
                profile.tilt_speed_code(SpeedCode(max(1, abs(tilt)))),
                pan_dir,
                tilt_dir,
            )
        case PanTiltAbsolute(pan_deg=pan, tilt_deg=tilt, pan_speed=ps, tilt_speed=ts):
            return codec_requests.PanTiltAbsolute(
                profile.pan_speed_code(SpeedCode(ps)),
                profile.tilt_speed_code(SpeedCode(ts)),
                profile.pan_to_counts(pan),
                profile.tilt_to_counts(tilt),
            )
        case PanTiltStop():
            return codec_requests.PanTiltDrive.stop()
        case PanTiltInquiry():
            return codec_requests.PanTiltPositionInquiry()
    raise TypeError(f"unknown scheduler action {action!r}")


def completion_timeout_s(
    request: ActionRequest, profile: CameraProfile, margin_s: float
) -> float | None:
    """How long a command's Completion may take on ``profile`` (None: the link's default).

    The camera's worst-case travel times a tolerance on the motor speed, plus ``margin_s``
    (as :class:`~drivers.visca.camera.Camera` bounds its own moves).
    """
    if isinstance(request, codec_requests.FocusDirect):
        return profile.focus_full_travel_s * MOVE_TIMEOUT_FACTOR + margin_s
    if isinstance(request, codec_requests.PanTiltAbsolute):
        pan_span = profile.pan_range_deg[1] - profile.pan_range_deg[0]
        tilt_span = profile.tilt_range_deg[1] - profile.tilt_range_deg[0]
        travel_s = max(
            pan_span / profile.pan_speeds_deg_s[request.pan_speed - 1],
            tilt_span / profile.tilt_speeds_deg_s[request.tilt_speed - 1],
        )
        return travel_s * MOVE_TIMEOUT_FACTOR + margin_s
    return None


def report_done(
    scheduler: Scheduler, action: Action, t: float, answer: object, profile: CameraProfile
) -> None:
    """``action`` succeeded at ``t`` (Completion, or ``answer`` to an inquiry): tell ``scheduler``.

    TypeError if an inquiry's answer is not the codec's reply to it.
    """
    match action:
        case FocusMove(move_id=move_id):
            scheduler.on_focus_completed(move_id, t)
        case FocusInquiry():
            if not isinstance(answer, codec_replies.FocusPosition):
                raise TypeError(f"FocusPosInq answered with {answer!r}")
            scheduler.on_focus_position(t, answer.counts)
        case PanTiltInquiry():
            if not isinstance(answer, codec_replies.PanTiltPosition):
                raise TypeError(f"Pan-tiltPosInq answered with {answer!r}")
            scheduler.on_pan_tilt_position(
                t,
                answer.pan / profile.pan_counts_per_deg,
                answer.tilt / profile.tilt_counts_per_deg,
            )
            scheduler.on_pan_tilt_done(t)
        case _:
            scheduler.on_pan_tilt_done(t)


def report_failed(scheduler: Scheduler, action: Action, t: float) -> None:
    """``action`` failed at ``t`` (error reply, timeout, out of range): tell ``scheduler``."""
    match action:
        case FocusMove(move_id=move_id):
            scheduler.on_focus_failed(move_id, t)
        case FocusInquiry():
            scheduler.on_focus_inquiry_failed(t)
        case _:
            scheduler.on_pan_tilt_failed(t)
