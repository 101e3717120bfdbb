"""The VISCA session's vocabulary: named timings, requests, events and counters.

Everything a shell of :class:`drivers.visca.session.ViscaSession` (the asyncio link, the
virtual-time bench) hands to it or gets back, apart from the state machine itself: the timings
(:class:`LinkTimeouts` and the module constants it defaults to), the request types
(:data:`SessionRequest`), the events (:data:`SessionEvent`) and :class:`SessionStats`. Import
them from here; :mod:`drivers.visca.session` holds only the state machine.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, TypeAlias

from drivers.visca.codec_replies import InquiryData
from drivers.visca.codec_requests import (
    Broadcast,
    CamPower,
    Cancel,
    Command,
    FocusDirect,
    FocusDirection,
    FocusDrive,
    FocusOnePush,
    PanDirection,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltHome,
    PanTiltRelative,
    PanTiltReset,
    TiltDirection,
    ZoomDirect,
)
from drivers.visca.errors import ViscaError

# ---- Named timings (seconds) -------------------------------------------------------------------
# A camera handles one message per video field (16.7 ms at 60 Hz, 20 ms at 50 Hz) and the wire
# carries 960 bytes/s at 9600 baud: a 16-byte command plus a 3-byte ACK is ~20 ms, so an answer
# is due ~40 ms after the write when the camera is idle, ~90 ms when it also has two commands
# and an inquiry to take in. The defaults leave a margin of ~3x over that for OS scheduling and
# USB-serial latency (FTDI latency timer 16 ms per direction).
FIELD_S = 1 / 60  # one video field at 60 Hz: the camera takes one message per field
ACK_TIMEOUT_S = 0.3
INQUIRY_TIMEOUT_S = 0.3
CANCEL_TIMEOUT_S = 0.3
# Address Set and broadcast IF_Clear are relayed by every camera of the chain (up to 7), each
# after taking it in: 7 x (1 field + 5 bytes) ~ 0.18 s, plus margin.
BROADCAST_TIMEOUT_S = 1.0
# Longest a request may wait in the queue for its turn: longer than the longest Completion
# timeout of a normal move below, so a queued command outlives the moves ahead of it.
QUEUE_TIMEOUT_S = 30.0
# After an ACK or inquiry timeout the answer may still be on its way; hold the next request of
# that kind this long so a straggler cannot be taken for the next request's answer (~6 fields).
LATE_REPLY_GUARD_S = 0.1
# Buffer full (a third command while two run) is never provoked by the session; if one comes
# (another controller, a lost ACK left a "ghost" command running), retry after a socket frees or
# after this pause (~3 fields), at most BUFFER_FULL_RETRIES times.
BUFFER_FULL_BACKOFF_S = 0.05
BUFFER_FULL_RETRIES = 3
# Reconnect backoff when the port vanished (used by the shells): first retry quickly (a USB
# re-enumeration takes ~0.1–1 s), then double up to a cap that keeps a replugged adapter in use
# within seconds.
RECONNECT_INITIAL_S = 0.1
RECONNECT_MAX_S = 5.0
# Re-initialising one camera (Address Set, IF_Clear, power-on, version, focus mode) after a
# reconnect or Network Change; power-on alone takes up to POWER_COMPLETION_TIMEOUT_S.
REINIT_TIMEOUT_S = 30.0

# Completion timeouts per command kind (the camera layer passes move-specific values).
# Focus Direct end to end takes ~2 s worst case on the EVI-D100 lens; Zoom Direct wide to tele
# ~2.5 s; Pan-tiltDrive and Focus Far/Near/Stop complete almost at once (the motion continues);
# One Push AF hunts for up to ~3 s; Home crosses at most half the pan range at high speed;
# Reset runs to both end stops and back; power-on initialises the pan/tilt mechanics (~7 s on
# the EVI-D70, whose manual gives it).
FOCUS_DIRECT_COMPLETION_TIMEOUT_S = 3.0
ZOOM_DIRECT_COMPLETION_TIMEOUT_S = 4.0
DRIVE_COMPLETION_TIMEOUT_S = 1.0
ONE_PUSH_AF_COMPLETION_TIMEOUT_S = 6.0
HOME_COMPLETION_TIMEOUT_S = 5.0
RESET_COMPLETION_TIMEOUT_S = 15.0
POWER_COMPLETION_TIMEOUT_S = 15.0
# Absolute/relative moves: the camera layer computes distance / speed; this is the fallback.
PAN_TILT_MOVE_COMPLETION_TIMEOUT_S = 20.0

COMMAND_QUEUE_MAX = 16  # per camera; a caller issuing faster than the camera runs gets an error
INQUIRY_QUEUE_MAX = 16  # per camera
BROADCAST_QUEUE_MAX = 8  # Address Set + IF_Clear per (re)initialisation; more is a caller bug
SOCKETS_PER_CAMERA = 2


@dataclass(frozen=True, slots=True)
class LinkTimeouts:
    """Every wait of the session and its shell, in seconds (defaults: the module constants)."""

    ack_s: float = ACK_TIMEOUT_S
    inquiry_s: float = INQUIRY_TIMEOUT_S
    cancel_s: float = CANCEL_TIMEOUT_S
    broadcast_s: float = BROADCAST_TIMEOUT_S
    queue_s: float = QUEUE_TIMEOUT_S
    late_reply_guard_s: float = LATE_REPLY_GUARD_S
    buffer_full_backoff_s: float = BUFFER_FULL_BACKOFF_S
    buffer_full_retries: int = BUFFER_FULL_RETRIES
    reconnect_initial_s: float = RECONNECT_INITIAL_S
    reconnect_max_s: float = RECONNECT_MAX_S
    reinit_s: float = REINIT_TIMEOUT_S
    completion_scale: float = 1.0  # multiplies every default Completion timeout

    def completion_s(self, request: Command) -> float:
        """Default Completion timeout for ``request`` (scaled by ``completion_scale``)."""
        return _default_completion_s(request) * self.completion_scale


class InquiryLike(Protocol):
    """An inquiry of the codec: ``to_message`` frames it, ``parse_reply`` types its answer."""

    def to_message(self) -> bytes: ...

    def parse_reply(self, data: bytes) -> InquiryData: ...


SessionRequest: TypeAlias = Command | InquiryLike | Broadcast | Cancel


# ---- events ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Acked:
    """The command of ``ticket`` was accepted into ``socket`` at ``t``."""

    ticket: int
    t: float
    socket: int


@dataclass(frozen=True, slots=True)
class Completed:
    """The command of ``ticket`` completed at ``t`` (final)."""

    ticket: int
    t: float


@dataclass(frozen=True, slots=True)
class Answered:
    """A non-command ticket's result (final).

    ``value`` is the parsed :class:`InquiryData` for an inquiry, the :data:`Reply` that came
    back for a broadcast, and for a Cancel True (cancelled) or False (the socket was idle).
    """

    ticket: int
    t: float
    value: Any


@dataclass(frozen=True, slots=True)
class Failed:
    """The request of ``ticket`` failed at ``t`` with ``error`` (final)."""

    ticket: int
    t: float
    error: ViscaError


@dataclass(frozen=True, slots=True)
class NetworkChanged:
    """Camera ``address`` reported a Network Change at ``t``: re-address and re-initialise.

    The session closed its gate; call :meth:`ViscaSession.open_gate` when re-initialised.
    """

    t: float
    address: int


SessionEvent: TypeAlias = Acked | Completed | Answered | Failed | NetworkChanged


@dataclass(frozen=True, slots=True)
class SessionStats:
    """The session's counters (all monotonic since it was created)."""

    bytes_in: int
    bytes_out: int
    packets_in: int
    packets_out: int
    replies: dict[str, int]
    errors_by_code: dict[int, int]
    timeouts: dict[str, int]
    dropped_bytes: int
    bad_packets: int
    stray_replies: int
    lost_completions: int
    resyncs: int
    buffer_full_retries: int
    network_changes: int
    last_reply_t: float | None


def is_stop(command: Command) -> bool:
    """True for Pan-tiltDrive Stop and Focus Stop (they jump the queue)."""
    if isinstance(command, PanTiltDrive):
        return command.pan is PanDirection.STOP and command.tilt is TiltDirection.STOP
    return isinstance(command, FocusDrive) and command.direction is FocusDirection.STOP


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _default_completion_s(request: Command) -> float:
    if isinstance(request, FocusDirect):
        return FOCUS_DIRECT_COMPLETION_TIMEOUT_S
    if isinstance(request, ZoomDirect):
        return ZOOM_DIRECT_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltAbsolute | PanTiltRelative):
        return PAN_TILT_MOVE_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltHome):
        return HOME_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltReset):
        return RESET_COMPLETION_TIMEOUT_S
    if isinstance(request, CamPower):
        return POWER_COMPLETION_TIMEOUT_S
    if isinstance(request, FocusOnePush):
        return ONE_PUSH_AF_COMPLETION_TIMEOUT_S
    return DRIVE_COMPLETION_TIMEOUT_S  # PanTiltDrive, FocusDrive, FocusMode
