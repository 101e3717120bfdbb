"""VISCA framing: the packet on the wire, the reassembler, and values one nibble per byte.

A packet is a header ``0x80 | sender << 4 | receiver``, 1–14 message bytes and the terminator
``FF`` (3–16 bytes; design.md §6.1). :class:`Packet` frames and parses one; :class:`Reassembler`
turns a byte stream into packets, resynchronising on ``FF``. Multi-byte values travel one nibble
per byte (``0p 0q 0r 0s``) so ``FF`` never occurs inside a packet: :func:`encode_u16` and its
kin. The addresses, :class:`CodecError` and the range and length checks every message uses live
here too, the base the request and reply modules build on. Split from :mod:`drivers.visca.codec`,
which keeps the entry points (typed message ↔ framed packet).
"""

from __future__ import annotations

from dataclasses import dataclass

TERMINATOR = 0xFF
MIN_PACKET_LEN = 3
MAX_PACKET_LEN = 16
CONTROLLER_ADDRESS = 0
BROADCAST_ADDRESS = 8
MIN_CAMERA_ADDRESS = 1
MAX_CAMERA_ADDRESS = 7
SOCKETS = (1, 2)


class CodecError(ValueError):
    """A byte sequence is not a valid VISCA packet or message."""


# --------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------


def check_range(name: str, value: int, low: int, high: int) -> int:
    """Return ``value`` if ``low <= value <= high`` else raise ValueError naming the field."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    if not low <= value <= high:
        raise ValueError(f"{name} = {value} is out of range [{low}, {high}] (0x{low:X}–0x{high:X})")
    return value


def encode_u16(value: int, name: str = "value") -> bytes:
    """Encode an unsigned 16-bit value as four nibble bytes, most significant first."""
    check_range(name, value, 0, 0xFFFF)
    return bytes((value >> shift) & 0x0F for shift in (12, 8, 4, 0))


def decode_u16(data: bytes) -> int:
    """Decode four nibble bytes into an unsigned 16-bit value."""
    if len(data) != 4 or any(b > 0x0F for b in data):
        raise CodecError(f"expected 4 nibble bytes, got {data.hex(' ')}")
    return (data[0] << 12) | (data[1] << 8) | (data[2] << 4) | data[3]


def encode_s16(value: int, name: str = "value") -> bytes:
    """Encode a signed 16-bit value (two's complement) as four nibble bytes."""
    check_range(name, value, -0x8000, 0x7FFF)
    return encode_u16(value & 0xFFFF)


def decode_s16(data: bytes) -> int:
    """Decode four nibble bytes into a signed 16-bit value."""
    raw = decode_u16(data)
    return raw - 0x10000 if raw & 0x8000 else raw


def expect_len(data: bytes, length: int, what: str) -> bytes:
    """Return ``data`` if it holds ``length`` bytes, else raise CodecError naming ``what``."""
    if len(data) != length:
        raise CodecError(f"{what} reply has {len(data)} data bytes, expected {length}")
    return data


# --------------------------------------------------------------------------------------------
# Framing
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Packet:
    """One framed VISCA packet: addressing plus the message bytes between header and FF."""

    sender: int  # 0 controller, 1–7 camera address, 8 + address on replies is folded back
    receiver: int  # 1–7 camera, 8 broadcast; 0 on replies to the controller
    message: bytes

    def to_bytes(self) -> bytes:
        """Serialise to wire bytes including header and terminator."""
        check_range("sender", self.sender, 0, 7)
        check_range("receiver", self.receiver, 0, 8)
        if not 1 <= len(self.message) <= MAX_PACKET_LEN - 2:
            raise ValueError(f"message length {len(self.message)} is out of range [1, 14]")
        if TERMINATOR in self.message:
            raise ValueError("message must not contain the terminator byte 0xFF")
        header = 0x80 | (self.sender << 4) | self.receiver
        return bytes((header, *self.message, TERMINATOR))

    @classmethod
    def from_bytes(cls, data: bytes) -> Packet:
        """Parse one complete packet; raise CodecError if it is not well formed."""
        if not MIN_PACKET_LEN <= len(data) <= MAX_PACKET_LEN:
            raise CodecError(f"packet length {len(data)} is out of range [3, 16]: {data.hex(' ')}")
        header = data[0]
        if header & 0x80 == 0 or header == TERMINATOR:
            raise CodecError(f"bad header byte 0x{header:02X}")
        if data[-1] != TERMINATOR:
            raise CodecError(f"packet does not end with FF: {data.hex(' ')}")
        message = data[1:-1]
        if TERMINATOR in message:
            raise CodecError(f"terminator inside packet: {data.hex(' ')}")
        return cls(sender=(header >> 4) & 0x07, receiver=header & 0x0F, message=bytes(message))

    @property
    def is_reply(self) -> bool:
        """True for camera → controller packets (receiver 0)."""
        return self.receiver == CONTROLLER_ADDRESS


def reply_header(camera_address: int) -> int:
    """The header byte a camera at ``camera_address`` uses on replies (``90`` for camera 1)."""
    check_range("camera address", camera_address, MIN_CAMERA_ADDRESS, MAX_CAMERA_ADDRESS)
    return (camera_address + 8) << 4


class Reassembler:
    """Turn arbitrary byte chunks into packets; resynchronise on FF, drop garbage, cap the buffer.

    A packet starts at a byte with the high bit set and ends at the next ``FF``. Bytes before a
    header, a partial packet interrupted by a new header, runs without a terminator longer than
    16 bytes, and terminated runs too short to be a packet are dropped and counted in
    :attr:`dropped_bytes`.
    """

    def __init__(self, max_packet_len: int = MAX_PACKET_LEN) -> None:
        self._buffer = bytearray()
        self._max = max_packet_len
        self._skip_to_terminator = False
        self.dropped_bytes = 0
        self.packets = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Consume ``data`` and return the complete raw packets found, in order."""
        found: list[bytes] = []
        for byte in data:
            if self._skip_to_terminator:
                self.dropped_bytes += 1
                self._skip_to_terminator = byte != TERMINATOR
                continue
            if not self._buffer:
                if byte & 0x80 == 0 or byte == TERMINATOR:
                    self.dropped_bytes += 1  # garbage before a header
                    continue
                self._buffer.append(byte)
                continue
            if byte & 0x80 and byte != TERMINATOR:
                # A header inside a packet: the terminator of the previous one was lost (noise).
                # Data bytes are nibbles or small codes below 0x80 in every message we use, so
                # restart here rather than merge two packets into one.
                self.dropped_bytes += len(self._buffer)
                self._buffer.clear()
            self._buffer.append(byte)
            if byte == TERMINATOR:
                if len(self._buffer) >= MIN_PACKET_LEN:
                    found.append(bytes(self._buffer))
                    self.packets += 1
                else:
                    self.dropped_bytes += len(self._buffer)
                self._buffer.clear()
            elif len(self._buffer) >= self._max:
                # No terminator where one must be: drop up to here and wait for the next FF.
                self.dropped_bytes += len(self._buffer)
                self._buffer.clear()
                self._skip_to_terminator = True
        return found

    def clear(self) -> int:
        """Discard a partial packet (stale input); return how many bytes were dropped."""
        dropped = len(self._buffer)
        self.dropped_bytes += dropped
        self._buffer.clear()
        self._skip_to_terminator = False
        return dropped

    @property
    def pending(self) -> int:
        """Bytes held of a packet not yet terminated."""
        return len(self._buffer)
