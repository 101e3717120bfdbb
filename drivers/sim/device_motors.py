"""The simulated camera's motors for its camera model: what they accept and how they move.

Pure functions of the :class:`~drivers.sim.state.CameraState` axes and the
:class:`~drivers.sim.models.SimModel`: the arguments the model's motors accept
(:func:`check_model_ranges`), the speed of a speed code, a Pan-tiltDrive, a full-speed move and
its travel time. :class:`~drivers.sim.device.ViscaDevice` calls them when it carries out a command.
"""

from __future__ import annotations

from drivers.sim.models import SimModel
from drivers.sim.state import CameraState
from drivers.visca import codec_framing, codec_requests


def check_model_ranges(request: codec_requests.Request, cam: SimModel) -> None:
    """Raise ValueError for arguments the wire format allows but the camera model does not."""
    pan_codes, tilt_codes = cam.max_pan_speed_code, cam.max_tilt_speed_code
    match request:
        case codec_requests.FocusDirect(counts=counts):
            codec_framing.check_range("focus counts", counts, *cam.focus_range)
        case codec_requests.ZoomDirect(counts=counts):
            codec_framing.check_range("zoom counts", counts, *cam.zoom_range)
        case codec_requests.PanTiltDrive(pan_speed=pan_speed, tilt_speed=tilt_speed):
            codec_framing.check_range("pan speed", pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", tilt_speed, 1, tilt_codes)
        case codec_requests.PanTiltAbsolute():
            codec_framing.check_range("pan speed", request.pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", request.tilt_speed, 1, tilt_codes)
            codec_framing.check_range("pan position", request.pan, *cam.pan_limit_counts)
            codec_framing.check_range("tilt position", request.tilt, *cam.tilt_limit_counts)
        case codec_requests.PanTiltRelative():
            codec_framing.check_range("pan speed", request.pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", request.tilt_speed, 1, tilt_codes)
            pan_low, pan_high = cam.pan_limit_counts
            tilt_low, tilt_high = cam.tilt_limit_counts
            span_pan, span_tilt = pan_high - pan_low, tilt_high - tilt_low
            codec_framing.check_range("pan offset", request.pan, -span_pan, span_pan)
            codec_framing.check_range("tilt offset", request.tilt, -span_tilt, span_tilt)
        case _:
            pass


def pan_speed_deg_s(cam: SimModel, code: int) -> float:
    """Pan speed in degrees per second for speed code ``code`` of ``cam``."""
    codec_framing.check_range("pan speed code", code, 1, cam.max_pan_speed_code)
    return cam.pan_speeds_deg_s[code - 1]


def tilt_speed_deg_s(cam: SimModel, code: int) -> float:
    """Tilt speed in degrees per second for speed code ``code`` of ``cam``."""
    codec_framing.check_range("tilt speed code", code, 1, cam.max_tilt_speed_code)
    return cam.tilt_speeds_deg_s[code - 1]


def drive_pan_tilt(
    st: CameraState, request: codec_requests.PanTiltDrive, t: float, cam: SimModel
) -> None:
    """Start (or stop) the pan and tilt drives ``request`` asks for at ``t``."""
    pan_dir = {codec_requests.PanDirection.LEFT: -1, codec_requests.PanDirection.RIGHT: 1}.get(
        request.pan
    )
    tilt_dir = {codec_requests.TiltDirection.DOWN: -1, codec_requests.TiltDirection.UP: 1}.get(
        request.tilt
    )
    if pan_dir is None:
        st.pan.stop(t)
    else:
        st.pan.drive(pan_dir, pan_speed_deg_s(cam, request.pan_speed), t)
    if tilt_dir is None:
        st.tilt.stop(t)
    else:
        st.tilt.drive(tilt_dir, tilt_speed_deg_s(cam, request.tilt_speed), t)


def move_pan_tilt(
    st: CameraState, pan_deg: float, tilt_deg: float, t: float, cam: SimModel
) -> float:
    """Move pan and tilt to ``pan_deg``, ``tilt_deg`` at full speed from ``t``; return the end."""
    return max(
        st.pan.move_to(pan_deg, cam.pan_speeds_deg_s[-1], t),
        st.tilt.move_to(tilt_deg, cam.tilt_speeds_deg_s[-1], t),
    )


def travel_s(pan_deg: float, tilt_deg: float, cam: SimModel) -> float:
    """Time of a full-speed move of ``pan_deg`` and ``tilt_deg`` (the slower axis's)."""
    return max(abs(pan_deg) / cam.pan_speeds_deg_s[-1], abs(tilt_deg) / cam.tilt_speeds_deg_s[-1])
