"""The VISCA link in virtual time: scheduler actions → codec bytes → the simulated device → events.

The lock-step bench drives the real device model (:class:`drivers.sim.device.ViscaDevice`, with
wire pacing at the configured baud and one message per video field) instead of assuming command
timings, so the depth rate it measures includes the link exactly as the simulated camera imposes
it. Replies are matched the way the real link does: the first reply to a request (ACK, an error,
or an inquiry answer) in send order, Completion per socket.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Literal

from dffd.scheduler import (
    Action,
    FocusInquiry,
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
)
from drivers.sim.device import COUNTS_PER_DEGREE, ViscaDevice
from drivers.visca import codec

logger = logging.getLogger(__name__)

CAMERA_ADDRESS = 1
# Requests awaiting their first reply. The device buffers at most two commands plus inquiries
# per field; anything deeper is a scheduler bug the bench should surface, not hide.
MAX_IN_FLIGHT = 8

EventKind = Literal[
    "focus_done", "focus_failed", "focus_position", "pt_done", "pt_failed", "pt_position"
]


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """What the controller learned at time ``t``."""

    t: float
    kind: EventKind
    move_id: int | None = None
    counts: int | None = None
    pan_deg: float | None = None
    tilt_deg: float | None = None


@dataclass(slots=True)
class _Pending:
    action: Action
    socket: int | None = None


class VirtualLink:
    """Executes scheduler actions on a :class:`ViscaDevice` and turns replies into events."""

    def __init__(self, device: ViscaDevice) -> None:
        self.device = device
        self._reassembler = codec.Reassembler()
        self._awaiting: deque[_Pending] = deque()  # first reply outstanding, in send order
        self._sockets: dict[int, _Pending] = {}  # ACKed commands awaiting Completion
        self.commands_sent = 0
        self.bytes_sent = 0
        self.errors = 0

    def send(self, action: Action, now: float) -> None:
        """Write the request for ``action`` at ``now``."""
        if len(self._awaiting) >= MAX_IN_FLIGHT:
            raise RuntimeError(f"more than {MAX_IN_FLIGHT} VISCA requests in flight")
        data = codec.encode_request(_request(action), CAMERA_ADDRESS)
        self.device.receive(data, now)
        self._awaiting.append(_Pending(action))
        self.commands_sent += 1
        self.bytes_sent += len(data)

    def next_deadline(self) -> float | None:
        """When the device next has something to do."""
        return self.device.next_deadline()

    def poll(self, t: float) -> list[LinkEvent]:
        """Advance the device to ``t``; return the events the replies mean."""
        events: list[LinkEvent] = []
        for emission in self.device.poll(t):
            for packet in self._reassembler.feed(emission.data):
                events.extend(self._on_packet(packet, emission.t))
        return events

    def _on_packet(self, raw: bytes, t: float) -> list[LinkEvent]:
        try:
            reply = codec.decode_reply(codec.Packet.from_bytes(raw))
        except codec.CodecError:
            logger.debug("undecodable reply %s", raw.hex(" "))
            return []
        match reply:
            case codec.Ack(socket=socket):
                if self._awaiting:
                    pending = self._awaiting.popleft()
                    pending.socket = socket
                    self._sockets[socket] = pending
                return []
            case codec.Completion(socket=socket):
                done = self._sockets.pop(socket, None)
                return [] if done is None else [_done(done.action, t)]
            case codec.ErrorReply(socket=socket):
                self.errors += 1
                failed = self._sockets.pop(socket, None)
                if failed is None and self._awaiting:
                    failed = self._awaiting.popleft()
                logger.debug("VISCA error %s at %.3f for %s", reply, t, failed)
                return [] if failed is None else [_failed(failed.action, t)]
            case codec.InquiryReply(data=data):
                if not self._awaiting:
                    return []
                pending = self._awaiting.popleft()
                return [_answer(pending.action, data, t)]
            case _:
                return []


def _request(action: Action) -> codec.Request:
    match action:
        case FocusMove(counts=counts):
            return codec.FocusDirect(counts)
        case FocusInquiry():
            return codec.FocusPositionInquiry()
        case PanTiltDrive(pan_speed=ps, tilt_speed=ts):
            pan_dir = (
                codec.PanDirection.STOP
                if ps == 0
                else (codec.PanDirection.RIGHT if ps > 0 else codec.PanDirection.LEFT)
            )
            tilt_dir = (
                codec.TiltDirection.STOP
                if ts == 0
                else (codec.TiltDirection.UP if ts > 0 else codec.TiltDirection.DOWN)
            )
            return codec.PanTiltDrive(max(1, abs(ps)), max(1, abs(ts)), pan_dir, tilt_dir)
        case PanTiltAbsolute(pan_deg=pan, tilt_deg=tilt, pan_speed=ps, tilt_speed=ts):
            return codec.PanTiltAbsolute(
                ps, ts, round(pan * COUNTS_PER_DEGREE), round(tilt * COUNTS_PER_DEGREE)
            )
        case PanTiltStop():
            return codec.PanTiltDrive.stop()
        case PanTiltInquiry():
            return codec.PanTiltPositionInquiry()
    raise TypeError(f"unknown scheduler action {action!r}")


def _done(action: Action, t: float) -> LinkEvent:
    if isinstance(action, FocusMove):
        return LinkEvent(t, "focus_done", move_id=action.move_id)
    return LinkEvent(t, "pt_done")


def _failed(action: Action, t: float) -> LinkEvent:
    if isinstance(action, FocusMove | FocusInquiry):
        return LinkEvent(t, "focus_failed", move_id=getattr(action, "move_id", None))
    return LinkEvent(t, "pt_failed")


def _answer(action: Action, data: bytes, t: float) -> LinkEvent:
    if isinstance(action, FocusInquiry):
        return LinkEvent(t, "focus_position", counts=codec.FocusPosition.from_data(data).counts)
    if isinstance(action, PanTiltInquiry):
        pos = codec.PanTiltPosition.from_data(data)
        return LinkEvent(
            t,
            "pt_position",
            pan_deg=pos.pan / COUNTS_PER_DEGREE,
            tilt_deg=pos.tilt / COUNTS_PER_DEGREE,
        )
    return LinkEvent(t, "pt_done")
