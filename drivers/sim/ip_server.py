"""The simulated camera over VISCA over IP (UDP): the camera's side of Sony's framing.

:class:`IpCameraEndpoint` is sans-IO: datagrams in (with the peer's address), VISCA bytes to the
:class:`~drivers.sim.device.ViscaDevice`, the device's replies back out in reply envelopes
carrying the sequence number of the request they answer. :class:`SimUdpServer` gives it a UDP
socket and a timer. The camera's rules, as Sony's VISCA-over-IP section describes them (see
:mod:`drivers.visca.ip` for the sources):

* RESET (control ``01``) empties the camera's memory of sequence numbers; answered ``01``;
* a command or inquiry whose sequence number the camera has already taken is not run again:
  control reply ``0F 01`` (sequence error) — a controller's retransmission after a lost reply;
* sequence number 0 is never a repeat (lax controllers send only zeros, the camera answers them);
* an unknown payload type, a VISCA command in an inquiry envelope (``01 10``), or a packet that
  is not VISCA gets ``0F 02`` (message-type error); an inquiry in a command envelope (``01 00``)
  is answered (lax controllers do that);
* replies: ACK/error/inquiry answer take the sequence number of the request they answer (the
  device answers requests in order), a Completion the number of the command that took its
  socket, a Network Change ``0``.

The set of remembered numbers (not "last + 1") is an assumption: Sony does not state whether a
camera rejects a gap or a reordered number; accepting any number not seen since the RESET is the
lenient reading, and the driver sends one datagram at a time anyway.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict, deque
from types import TracebackType
from typing import Self, cast

from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import Faults, FaultSpec
from drivers.sim.state import CameraState
from drivers.visca.ip import (
    CONTROL_MESSAGE_TYPE_ERROR,
    CONTROL_RESET,
    CONTROL_RESET_ACK,
    CONTROL_SEQUENCE_ERROR,
    IpFrameError,
    PayloadType,
    decode_datagram,
    encode_datagram,
)

logger = logging.getLogger(__name__)

Address = tuple[str, int]
# Sequence numbers the camera remembers since the last RESET (a retransmission comes within a
# second; a controller sends tens per second at most).
SEEN_MEMORY = 256
# Requests answered in order whose first reply has not left the camera yet: the device's input
# queue holds 16 packets, so more pending here means replies were lost inside the device.
PENDING_MAX = 32


class IpCameraEndpoint:
    """Camera side of VISCA over IP for one :class:`ViscaDevice`, fed datagrams and time."""

    def __init__(self, device: ViscaDevice) -> None:
        self.device = device
        self.sequence_errors = 0
        self.message_type_errors = 0
        self.resets = 0
        self._seen: OrderedDict[int, None] = OrderedDict()
        self._first: deque[tuple[int, Address]] = deque()  # requests awaiting their first reply
        self._socket_seq: dict[int, tuple[int, Address]] = {}
        self._peer: Address | None = None
        self._out: list[tuple[bytes, Address]] = []
        self._rx = bytearray()

    def receive(self, datagram: bytes, peer: Address, now: float) -> None:
        """One datagram from a controller at ``peer``."""
        self._peer = peer
        try:
            msg = decode_datagram(datagram)
        except IpFrameError as exc:
            logger.debug("sim camera: bad datagram from %s: %s", peer, exc)
            return
        if msg.kind == PayloadType.CONTROL:
            if msg.payload == CONTROL_RESET:
                self.resets += 1
                self._seen.clear()
                self._reply(PayloadType.CONTROL_REPLY, msg.seq, CONTROL_RESET_ACK, peer)
            else:
                self._type_error(msg.seq, peer)
            return
        packet = msg.payload
        is_visca = len(packet) >= 3 and packet[0] & 0x80 and packet[-1] == 0xFF
        envelope_ok = msg.kind in (PayloadType.COMMAND, PayloadType.DEVICE_SETTING) or (
            msg.kind == PayloadType.INQUIRY and len(packet) >= 2 and packet[1] == 0x09
        )
        if not is_visca or not envelope_ok:
            self._type_error(msg.seq, peer)
            return
        if msg.seq != 0:
            if msg.seq in self._seen:
                self.sequence_errors += 1
                self._reply(PayloadType.CONTROL_REPLY, msg.seq, CONTROL_SEQUENCE_ERROR, peer)
                return
            self._seen[msg.seq] = None
            while len(self._seen) > SEEN_MEMORY:
                self._seen.popitem(last=False)
        if len(self._first) >= PENDING_MAX:
            self._first.popleft()
        if packet[0] != 0x88:  # broadcasts are echoed, not answered per request
            self._first.append((msg.seq, peer))
        self.device.receive(packet, now)

    def poll(self, now: float) -> None:
        """Run the device up to ``now`` and frame what it sent."""
        for emission in self.device.poll(now):
            self._rx += emission.data
            while (end := self._rx.find(b"\xff")) >= 0:
                packet = bytes(self._rx[: end + 1])
                del self._rx[: end + 1]
                self._frame(packet)

    def next_deadline(self) -> float | None:
        """When :meth:`poll` must run next."""
        return self.device.next_deadline()

    def datagrams_to_send(self) -> list[tuple[bytes, Address]]:
        """Datagrams with their destination (taken)."""
        out, self._out = self._out, []
        return out

    def _frame(self, packet: bytes) -> None:
        kind = packet[1] & 0xF0 if len(packet) >= 3 else 0
        socket = packet[1] & 0x0F if len(packet) >= 3 else 0
        peer = self._peer
        if packet[0] == 0x88 or kind == 0x30:  # broadcast echo / Network Change / Address Set
            if peer is not None:
                self._reply(PayloadType.REPLY, 0, packet, peer)
            return
        if kind == 0x50 and len(packet) == 3 and socket in self._socket_seq:
            seq, peer = self._socket_seq.pop(socket)  # Completion of a running command
        elif self._first:
            seq, peer = self._first.popleft()
            if kind == 0x40:
                self._socket_seq[socket] = (seq, peer)
            elif kind == 0x60 and packet[2] in (0x04,) and socket in self._socket_seq:
                del self._socket_seq[socket]  # cancelled: no Completion follows
        else:
            seq = 0
        if peer is not None:
            self._reply(PayloadType.REPLY, seq, packet, peer)

    def _type_error(self, seq: int, peer: Address) -> None:
        self.message_type_errors += 1
        self._reply(PayloadType.CONTROL_REPLY, seq, CONTROL_MESSAGE_TYPE_ERROR, peer)

    def _reply(self, kind: PayloadType, seq: int, payload: bytes, peer: Address) -> None:
        self._out.append((encode_datagram(kind, seq, payload), peer))


class SimUdpServer(asyncio.DatagramProtocol):
    """Serve the simulated camera as VISCA over IP on ``host:port`` (0: any free port)."""

    def __init__(
        self,
        config: DeviceConfig | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        faults: Faults | FaultSpec | str | None = None,
        state: CameraState | None = None,
    ) -> None:
        self.config = config or DeviceConfig()
        self.faults = faults if isinstance(faults, Faults) else Faults(faults)
        self.state = state or CameraState(clock=time.monotonic)
        self.device = ViscaDevice(self.state, self.config, self.faults)
        self.endpoint = IpCameraEndpoint(self.device)
        self.host = host
        self.port = port
        self._clock = self.state.clock
        self._udp: asyncio.DatagramTransport | None = None
        self._timer: asyncio.TimerHandle | None = None

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    @property
    def url(self) -> str:
        """What a controller connects to: ``visca-ip://host:port``."""
        return f"visca-ip://{self.host}:{self.port}"

    async def start(self) -> None:
        """Bind the socket, power the camera up."""
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: self, local_addr=(self.host, self.port))
        assert self._udp is not None
        self.port = self._udp.get_extra_info("sockname")[1]
        self.device.power_up(self._clock())
        self._pump()
        logger.info("sim camera: serving VISCA over IP on %s", self.url)

    async def stop(self) -> None:
        """Close the socket."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._udp is not None:
            self._udp.close()
            self._udp = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # 3.11's selector datagram transport does not subclass DatagramTransport.
        self._udp = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.endpoint.receive(data, (addr[0], addr[1]), self._clock())
        self._pump()

    def error_received(self, exc: Exception) -> None:
        logger.debug("sim camera: UDP error %s", exc)

    def _pump(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._udp is None:
            return
        self.endpoint.poll(self._clock())
        for datagram, peer in self.endpoint.datagrams_to_send():
            self._udp.sendto(datagram, peer)
        deadline = self.endpoint.next_deadline()
        if deadline is not None:
            delay = max(0.0, deadline - self._clock())
            self._timer = asyncio.get_running_loop().call_later(delay, self._pump)
