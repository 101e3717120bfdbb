"""VISCA over IP (Sony's UDP framing, port 52381): the envelope codec and the controller's channel.

Each datagram is an 8-byte header then one VISCA packet (or a control payload)::

    payload type (2 bytes) | payload length (2 bytes) | sequence number (4 bytes, big-endian)

Payload types: ``01 00`` VISCA command, ``01 10`` inquiry, ``01 11`` reply, ``01 20`` device
setting, ``02 00`` control command, ``02 01`` control reply. Control command ``01`` (RESET)
restarts the sequence and is answered by control reply ``01``; a camera reports a bad sequence
number with control reply ``0F 01`` and a bad payload type with ``0F 02``. Sources: Sony's
"VISCA over IP" section as reproduced in the NewTek NDI HX PTZ3 and AViPAS AV-2010 manuals
(manualshive.com), which also give the delivery rule used here: the controller waits for a reply,
resends on timeout with the *same* sequence number, and a camera that already had that number
answers ``0F 01`` ("the command has been performed"; for an inquiry, ask again with a new one).

:func:`encode_datagram` / :func:`decode_datagram` are the pure codec. :class:`IpChannel` is the
sans-IO controller side under :class:`drivers.visca.session.ViscaSession`: it takes the session's
VISCA packets, sends them one datagram at a time (stop-and-wait, as the spec's controllers do, so
a camera that checks the order never sees a gap), retransmits, matches replies by the sequence
number the camera echoes and hands the session a clean VISCA byte stream:

* a duplicated reply (same sequence number, same kind) is dropped;
* a Completion (or error) that arrives before its ACK — the ACK was lost or overtaken — gets
  the ACK put in front of it, taken from the Completion's socket;
* one VISCA-over-IP address is one camera (address 1): Address Set is answered here (a chain of
  one) and the IF_Clear broadcast is sent as the camera's own IF_Clear, its reply given to the
  session as the broadcast's echo;
* lax cameras: a camera that answers with sequence number 0 (no echo) is matched in order; one
  that answers ``0F 02`` to an inquiry envelope gets inquiries in a command envelope afterwards.
"""

from __future__ import annotations

import logging
from collections import OrderedDict, deque
from dataclasses import dataclass
from enum import IntEnum

logger = logging.getLogger(__name__)
TRACE = 5  # raw datagrams are logged below DEBUG

HEADER_LEN = 8
MAX_PAYLOAD = 16  # a VISCA packet is 3–16 bytes; control payloads are 1–2
SEQ_MOD = 1 << 32

CONTROL_RESET = b"\x01"
CONTROL_RESET_ACK = b"\x01"
CONTROL_SEQUENCE_ERROR = b"\x0f\x01"
CONTROL_MESSAGE_TYPE_ERROR = b"\x0f\x02"

# Retransmission: a LAN camera answers within one video field (16.7 ms) plus its network stack;
# 60 ms is ~3 fields. Three retransmissions fit inside the session's 0.3 s ACK/inquiry wait.
RETRANSMIT_S = 0.06
MAX_RETRANSMITS = 3
# Bound on packets waiting for their turn: the session keeps at most one command awaiting its
# ACK, one inquiry, Cancels and stops per camera, so more than this is a runaway caller.
SEND_QUEUE_MAX = 32
# How many recent sequence numbers keep their reply state (for duplicates and late ACKs).
SEQ_MEMORY = 64


class PayloadType(IntEnum):
    """The header's payload type."""

    COMMAND = 0x0100
    INQUIRY = 0x0110
    REPLY = 0x0111
    DEVICE_SETTING = 0x0120
    CONTROL = 0x0200
    CONTROL_REPLY = 0x0201


class IpFrameError(ValueError):
    """A datagram that is not a VISCA-over-IP message (too short, length mismatch)."""


@dataclass(frozen=True, slots=True)
class Datagram:
    """One VISCA-over-IP message: payload type (any 16-bit value), sequence number, payload."""

    kind: int
    seq: int
    payload: bytes

    def encode(self) -> bytes:
        """The datagram's bytes (header + payload)."""
        return encode_datagram(self.kind, self.seq, self.payload)


def encode_datagram(kind: int, seq: int, payload: bytes) -> bytes:
    """Header + payload; ValueError for a payload type, sequence number or length out of range."""
    if not 0 <= kind <= 0xFFFF:
        raise ValueError(f"payload type {kind:#x} is not a 16-bit value")
    if not 0 <= seq < SEQ_MOD:
        raise ValueError(f"sequence number {seq} is not a 32-bit value")
    if not 1 <= len(payload) <= MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes; VISCA over IP carries 1–16")
    return (
        kind.to_bytes(2, "big")
        + len(payload).to_bytes(2, "big")
        + seq.to_bytes(4, "big")
        + (payload)
    )


def decode_datagram(data: bytes) -> Datagram:
    """Parse one datagram; IpFrameError when the header is short or its length is wrong."""
    if len(data) < HEADER_LEN + 1:
        raise IpFrameError(f"{len(data)}-byte datagram: shorter than a header and one byte")
    kind = int.from_bytes(data[0:2], "big")
    length = int.from_bytes(data[2:4], "big")
    seq = int.from_bytes(data[4:8], "big")
    payload = data[HEADER_LEN:]
    if length != len(payload) or not 1 <= length <= MAX_PAYLOAD:
        raise IpFrameError(f"header says {length} payload bytes, datagram carries {len(payload)}")
    return Datagram(kind, seq, bytes(payload))


def payload_type_for(packet: bytes) -> PayloadType:
    """The envelope a controller uses for a VISCA packet (``8x 09`` inquiry, else command)."""
    if len(packet) >= 2 and packet[1] == 0x09:
        return PayloadType.INQUIRY
    return PayloadType.COMMAND


ADDRESS_SET = bytes.fromhex("883001ff")
IF_CLEAR_BROADCAST = bytes.fromhex("88010001ff")
IF_CLEAR_CAMERA_1 = bytes.fromhex("81010001ff")


@dataclass(slots=True)
class _Out:
    kind: PayloadType
    payload: bytes
    echo_as: bytes | None = None  # the reply is handed on as these bytes (IF_Clear broadcast)
    shares: int | None = None  # a resent inquiry: the sequence number whose reply state it shares
    seq: int = 0
    sent: int = 0  # transmissions so far
    deadline: float = 0.0
    refused: bool = False  # the camera answered our first send with a sequence error


@dataclass(slots=True)
class _Seen:
    command: bool
    acked: bool = False
    done: bool = False


@dataclass(slots=True)
class IpStats:
    """Counters of one channel (for health reports and tests)."""

    sent: int = 0
    retransmits: int = 0
    given_up: int = 0
    duplicates: int = 0
    acks_restored: int = 0
    sequence_errors: int = 0
    message_type_errors: int = 0
    resets: int = 0
    bad_datagrams: int = 0


class IpChannel:
    """Sans-IO controller side of VISCA over IP: VISCA packets in, datagrams out, and back."""

    def __init__(
        self,
        *,
        retransmit_s: float = RETRANSMIT_S,
        max_retransmits: int = MAX_RETRANSMITS,
        queue_max: int = SEND_QUEUE_MAX,
    ) -> None:
        self.retransmit_s = retransmit_s
        self.max_retransmits = max_retransmits
        self.queue_max = queue_max
        self.stats = IpStats()
        self.camera_echoes_seq = True
        self.inquiry_envelope = PayloadType.INQUIRY
        self._next_seq = 0
        self._queue: deque[_Out] = deque()
        self._pending: _Out | None = None
        self._seen: OrderedDict[int, _Seen] = OrderedDict()
        self._socket_seq: dict[int, int] = {}  # socket → sequence number of its last ACK
        self._datagrams: list[bytes] = []
        self._data = bytearray()

    def connection_made(self, now: float) -> None:
        """Start (or restart) the sequence: RESET goes out before anything queued."""
        self._seen.clear()
        self._socket_seq.clear()
        if self._pending is not None and self._pending.kind is not PayloadType.CONTROL:
            self._queue.appendleft(self._pending)
        self._pending = None
        self._queue.appendleft(_Out(PayloadType.CONTROL, CONTROL_RESET))
        self.stats.resets += 1
        self._pump(now)

    def send(self, packet: bytes, now: float) -> None:
        """Queue one VISCA packet from the session; OSError if the queue is full."""
        if packet == ADDRESS_SET:
            # One camera per address: the chain is camera 1 alone, next address 2.
            self._data += bytes.fromhex("883002ff")
            return
        if len(self._queue) >= self.queue_max:
            raise OSError(f"VISCA-over-IP send queue full ({self.queue_max} packets)")
        if packet == IF_CLEAR_BROADCAST:
            out = _Out(PayloadType.COMMAND, IF_CLEAR_CAMERA_1, echo_as=IF_CLEAR_BROADCAST)
        else:
            kind = payload_type_for(packet)
            if kind is PayloadType.INQUIRY:
                kind = self.inquiry_envelope
            out = _Out(kind, packet)
        self._queue.append(out)
        self._pump(now)

    def receive(self, datagram: bytes, now: float) -> None:
        """Take one datagram from the camera (VISCA bytes then wait in :meth:`data_received`)."""
        try:
            msg = decode_datagram(datagram)
        except IpFrameError as exc:
            self.stats.bad_datagrams += 1
            logger.debug("VISCA over IP: dropped datagram %s: %s", datagram.hex(" "), exc)
            return
        logger.log(
            TRACE, "VISCA over IP << %04x seq %d: %s", msg.kind, msg.seq, msg.payload.hex(" ")
        )
        if msg.kind == PayloadType.CONTROL_REPLY:
            self._on_control_reply(msg, now)
        elif msg.kind == PayloadType.REPLY:
            self._on_reply(msg, now)
        else:
            self.stats.bad_datagrams += 1
            logger.debug("VISCA over IP: ignored payload type %#06x from the camera", msg.kind)

    def poll(self, now: float) -> None:
        """Retransmit (same sequence number) or give up on a datagram whose reply is overdue."""
        out = self._pending
        if out is None or now < out.deadline:
            return
        if out.refused:
            # The camera refused our sequence number and nothing else came: it lost the
            # sequence (restarted, another controller). RESET, then send under a new number.
            logger.info("VISCA over IP: sequence error from the camera; resetting the sequence")
            self._pending = None
            # The refused number may still be answered late (a duplicate of it was what the
            # camera refused): the resend shares its reply state, so one answer reaches the
            # session, whichever number it comes under.
            self._queue.appendleft(_Out(out.kind, out.payload, out.echo_as, shares=out.seq))
            self._queue.appendleft(_Out(PayloadType.CONTROL, CONTROL_RESET))
            self.stats.resets += 1
            self._pump(now)
            return
        if out.sent <= self.max_retransmits:
            self.stats.retransmits += 1
            self._transmit(out, now)
            return
        self.stats.given_up += 1
        logger.debug("VISCA over IP: no reply to seq %d after %d sends", out.seq, out.sent)
        self._pending = None  # the session's own timeout reports it
        self._pump(now)

    def socket_done(self, socket: int) -> None:
        """The command ACKed in ``socket`` is over (found by inquiry): drop its late replies."""
        seq = self._socket_seq.pop(socket, None)
        seen = self._seen.get(seq) if seq is not None else None
        if seen is not None:
            seen.done = True

    def next_deadline(self) -> float | None:
        """When :meth:`poll` must run next (None: nothing in flight)."""
        return None if self._pending is None else self._pending.deadline

    def datagrams_to_send(self) -> list[bytes]:
        """The datagrams to write, in order (taken)."""
        out, self._datagrams = self._datagrams, []
        return out

    def data_received(self) -> bytes:
        """The VISCA bytes for the session (taken)."""
        data = bytes(self._data)
        self._data.clear()
        return data

    # ---- internals ------------------------------------------------------------------------

    def _pump(self, now: float) -> None:
        if self._pending is not None or not self._queue:
            return
        out = self._queue.popleft()
        if out.kind is PayloadType.CONTROL:
            out.seq = 0  # RESET: "the value set as the sequence number is ignored"
        else:
            out.seq = self._take_seq()
            # IF_Clear is answered z0 50 FF without an ACK: not a command for reply matching.
            acked = out.kind is PayloadType.COMMAND and out.payload[1:4] != IF_CLEAR_CAMERA_1[1:4]
            shared = self._seen.get(out.shares) if out.shares is not None else None
            self._remember(out.seq, shared or _Seen(command=acked and out.payload[1] != 0x09))
        self._pending = out
        self._transmit(out, now)

    def _take_seq(self) -> int:
        # 0 is what lax peers send for "no sequence"; skip it so every number we use is unique.
        self._next_seq = (self._next_seq + 1) % SEQ_MOD or 1
        return self._next_seq

    def _transmit(self, out: _Out, now: float) -> None:
        out.sent += 1
        out.deadline = now + self.retransmit_s
        self.stats.sent += 1
        logger.log(
            TRACE, "VISCA over IP >> %04x seq %d: %s", out.kind, out.seq, out.payload.hex(" ")
        )
        self._datagrams.append(encode_datagram(out.kind, out.seq, out.payload))

    def _remember(self, seq: int, seen: _Seen) -> None:
        self._seen[seq] = seen
        while len(self._seen) > SEQ_MEMORY:
            self._seen.popitem(last=False)

    def _matches_pending(self, seq: int) -> bool:
        pending = self._pending
        if pending is None:
            return False
        if seq == pending.seq:
            return True
        if seq == 0 and pending.kind is not PayloadType.CONTROL:
            self.camera_echoes_seq = False  # lax camera: replies carry no sequence number
            return True
        return False

    def _seen_command(self, seq: int) -> bool:
        seen = self._seen.get(seq)
        return seen is not None and seen.command

    def _on_control_reply(self, msg: Datagram, now: float) -> None:
        pending = self._pending
        if msg.payload == CONTROL_RESET_ACK:
            if pending is not None and pending.kind is PayloadType.CONTROL:
                self._pending = None
                self._pump(now)
            return
        if msg.payload == CONTROL_SEQUENCE_ERROR:
            self.stats.sequence_errors += 1
            if pending is None or pending.kind is PayloadType.CONTROL:
                return
            if msg.seq not in (pending.seq, 0):
                return  # about an older datagram (a late duplicate): nothing waits for it
            if pending.sent == 1:
                # Our only send refused: either a duplicate of it reached the camera second
                # (its real reply follows within a field) or the camera lost our sequence.
                # poll() decides when the retransmission time comes and nothing else did.
                pending.refused = True
                return
            self._pending = None
            if pending.kind is PayloadType.INQUIRY or not self._seen_command(pending.seq):
                # A resent inquiry the camera already answered (the answer was lost or is late):
                # ask again under a new number that shares the old one's reply state, so the
                # session gets exactly one answer, whichever comes first.
                self._queue.appendleft(
                    _Out(pending.kind, pending.payload, pending.echo_as, shares=pending.seq)
                )
            # A resent command the camera already has: it has been performed; its ACK was lost
            # (or is late) and the Completion restores it (see _fresh).
            self._pump(now)
            return
        if msg.payload == CONTROL_MESSAGE_TYPE_ERROR:
            self.stats.message_type_errors += 1
            if pending is not None and pending.kind is PayloadType.INQUIRY:
                logger.warning(
                    "VISCA over IP: the camera refuses inquiries in an inquiry envelope (01 10); "
                    "sending them as commands (01 00) from now on"
                )
                self.inquiry_envelope = PayloadType.COMMAND
                self._pending = None
                self._queue.appendleft(_Out(PayloadType.COMMAND, pending.payload, pending.echo_as))
                self._pump(now)
            return
        self.stats.bad_datagrams += 1

    def _on_reply(self, msg: Datagram, now: float) -> None:
        data = msg.payload
        pending = self._pending
        matched = self._matches_pending(msg.seq)
        seen = self._seen.get(msg.seq) if msg.seq else None
        kind = (data[1] & 0xF0) if len(data) >= 3 else 0
        if kind == 0x40 and msg.seq:
            self._socket_seq[data[1] & 0x0F] = msg.seq
        shares_pending = (
            pending is not None and seen is not None and self._seen.get(pending.seq) is seen
        )
        if seen is not None and not self._fresh(seen, kind, data):
            self.stats.duplicates += 1
            if matched and pending is not None:
                # The answer already reached the session under a number this one shares (a
                # resent inquiry): nothing more to wait for — keep the line moving.
                self._pending = None
                self._pump(now)
            return
        if not matched and shares_pending and seen is not None and seen.done:
            # A late answer to the older number the pending resend shares its reply state with:
            # the session has its answer, so the resend is answered too (left pending, it would
            # be resent, refused "already performed" and asked again for ever, stalling the line).
            matched = True
        if matched and pending is not None:
            self._pending = None
            if pending.echo_as is not None and kind == 0x50:
                data = pending.echo_as
        self._data += data
        if matched:
            self._pump(now)

    def _fresh(self, seen: _Seen, kind: int, data: bytes) -> bool:
        """Update a sequence number's reply state; False for a duplicate or a stale reply."""
        if seen.done:
            return False
        if kind == 0x40:  # ACK
            if seen.acked or not seen.command:
                return False
            seen.acked = True
            return True
        if seen.command and not seen.acked and kind == 0x50 and len(data) == 3:
            # A Completion before its ACK: put the ACK (same socket) in front of it.
            self.stats.acks_restored += 1
            self._data += bytes((data[0], 0x40 | (data[1] & 0x0F), 0xFF))
        seen.done = kind in (0x50, 0x60)
        return True
