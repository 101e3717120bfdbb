"""The VISCA link in virtual time: scheduler actions → codec bytes → the simulated device → events.

The lock-step bench drives the real device model (:class:`drivers.sim.device.ViscaDevice`, with
wire pacing at the configured baud and one message per video field) instead of assuming command
timings, so the depth rate it measures includes the link exactly as the simulated camera imposes
it. Actions become requests by the service's own translation (:func:`dffd.actuation.request_for`
with the driver's camera profile). Replies are matched the way the real link does: the first
reply to a request (ACK, an error, or an inquiry answer) in send order, Completion per socket.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

from dffd.actuation import ActionRequest, request_for
from dffd.scheduler import Action
from drivers.sim.device import ViscaDevice
from drivers.visca import codec
from drivers.visca.camera import CameraProfile

logger = logging.getLogger(__name__)

CAMERA_ADDRESS = 1
# Requests awaiting their first reply. The device buffers at most two commands plus inquiries
# per field; anything deeper is a scheduler bug the bench should surface, not hide.
MAX_IN_FLIGHT = 8


@dataclass(frozen=True, slots=True)
class Outcome:
    """How ``action`` ended at ``t``: done (with the inquiry's ``answer``) or failed."""

    action: Action
    t: float
    ok: bool
    answer: object = None


@dataclass(slots=True)
class _Pending:
    action: Action
    request: ActionRequest
    socket: int | None = None


class VirtualLink:
    """Executes scheduler actions on a :class:`ViscaDevice` and turns replies into outcomes."""

    def __init__(self, device: ViscaDevice, profile: CameraProfile) -> None:
        self.device = device
        self.profile = profile
        self._reassembler = codec.Reassembler()
        self._awaiting: deque[_Pending] = deque()  # first reply outstanding, in send order
        self._sockets: dict[int, _Pending] = {}  # ACKed commands awaiting Completion
        self.commands_sent = 0
        self.bytes_sent = 0
        self.errors = 0

    def send(self, action: Action, now: float) -> list[Outcome]:
        """Write the request for ``action`` at ``now`` (an action out of range fails at once)."""
        if len(self._awaiting) >= MAX_IN_FLIGHT:
            raise RuntimeError(f"more than {MAX_IN_FLIGHT} VISCA requests in flight")
        try:
            request = request_for(action, self.profile)
        except ValueError as exc:
            logger.debug("action %r not sent: %s", action, exc)
            return [Outcome(action, now, ok=False)]
        data = codec.encode_request(request, CAMERA_ADDRESS)
        self.device.receive(data, now)
        self._awaiting.append(_Pending(action, request))
        self.commands_sent += 1
        self.bytes_sent += len(data)
        return []

    def next_deadline(self) -> float | None:
        """When the device next has something to do."""
        return self.device.next_deadline()

    def poll(self, t: float) -> list[Outcome]:
        """Advance the device to ``t``; return the outcomes the replies mean."""
        events: list[Outcome] = []
        for emission in self.device.poll(t):
            for packet in self._reassembler.feed(emission.data):
                events.extend(self._on_packet(packet, emission.t))
        return events

    def _on_packet(self, raw: bytes, t: float) -> list[Outcome]:
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
                return [] if done is None else [Outcome(done.action, t, ok=True)]
            case codec.ErrorReply(socket=socket):
                self.errors += 1
                failed = self._sockets.pop(socket, None)
                if failed is None and self._awaiting:
                    failed = self._awaiting.popleft()
                logger.debug("VISCA error %s at %.3f for %s", reply, t, failed)
                return [] if failed is None else [Outcome(failed.action, t, ok=False)]
            case codec.InquiryReply(data=data):
                if not self._awaiting:
                    return []
                pending = self._awaiting.popleft()
                request = pending.request
                if not isinstance(
                    request, codec.FocusPositionInquiry | codec.PanTiltPositionInquiry
                ):
                    return [Outcome(pending.action, t, ok=False)]  # an answer to a command
                try:
                    answer = request.parse_reply(data)
                except codec.CodecError:
                    return [Outcome(pending.action, t, ok=False)]
                return [Outcome(pending.action, t, ok=True, answer=answer)]
            case _:
                return []
