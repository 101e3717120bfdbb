"""Sans-IO VISCA codec: framing, typed commands and replies, nibble encoding, reassembly.

Pure functions and frozen dataclasses only; both the driver (controller side) and the simulated
camera (device side) use this module, so a packet is encoded and decoded in exactly one place.

Framing (design.md §6): header ``0x80 | sender << 4 | receiver``, 1–14 message bytes, terminator
``FF``; packets are 3–16 bytes. Multi-byte values travel one nibble per byte (``0p 0q 0r 0s``) so
``FF`` never occurs inside a packet.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import ClassVar, Generic, Literal, Self, TypeAlias, TypeVar, cast

TERMINATOR = 0xFF
MIN_PACKET_LEN = 3
MAX_PACKET_LEN = 16
CONTROLLER_ADDRESS = 0
BROADCAST_ADDRESS = 8
MIN_CAMERA_ADDRESS = 1
MAX_CAMERA_ADDRESS = 7
SOCKETS = (1, 2)

# Speed ranges accepted by the wire format. Model profiles (camera.py) narrow these further;
# 0x18 is the widest pan speed of the EVI family, 0x17 the widest tilt speed (EVI-D70).
PAN_SPEED_RANGE = (0x01, 0x18)
TILT_SPEED_RANGE = (0x01, 0x17)
FOCUS_SPEED_RANGE = (0, 7)


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


# --------------------------------------------------------------------------------------------
# Replies (camera → controller)
# --------------------------------------------------------------------------------------------


class ErrorCode(enum.IntEnum):
    """VISCA error codes carried in ``z0 6y EE FF``."""

    MESSAGE_LENGTH = 0x01
    SYNTAX = 0x02
    BUFFER_FULL = 0x03
    CANCELLED = 0x04
    NO_SOCKET = 0x05
    NOT_EXECUTABLE = 0x41

    @classmethod
    def describe(cls, code: int) -> str:
        """Human-readable name of ``code`` (also for codes outside the enum)."""
        try:
            return cls(code).name.lower().replace("_", " ")
        except ValueError:
            return f"unknown error 0x{code:02X}"


@dataclass(frozen=True, slots=True)
class Ack:
    """Command accepted into ``socket``."""

    socket: int

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return bytes((0x40 | check_range("socket", self.socket, 1, 2),))


@dataclass(frozen=True, slots=True)
class Completion:
    """Command in ``socket`` finished."""

    socket: int

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return bytes((0x50 | check_range("socket", self.socket, 1, 2),))


@dataclass(frozen=True, slots=True)
class ErrorReply:
    """An error for the command in ``socket`` (0 when no socket is involved)."""

    socket: int
    code: int

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        check_range("socket", self.socket, 0, 0x0F)
        return bytes((0x60 | self.socket, check_range("error code", self.code, 0, 0x7F)))


@dataclass(frozen=True, slots=True)
class InquiryReply:
    """``z0 50 … FF``: data answering an inquiry (also the reply to a per-camera IF_Clear)."""

    data: bytes

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        if len(self.data) > 13:
            raise ValueError(f"inquiry data length {len(self.data)} exceeds 13")
        return b"\x50" + self.data


@dataclass(frozen=True, slots=True)
class NetworkChange:
    """Unsolicited ``z0 38 FF``: the chain changed; the controller must redo Address Set."""

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return b"\x38"


@dataclass(frozen=True, slots=True)
class AddressSetReply:
    """``88 30 0w FF`` back from the end of the chain: ``next_address`` = last address + 1."""

    next_address: int

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return bytes((0x30, check_range("next address", self.next_address, 1, 8)))


@dataclass(frozen=True, slots=True)
class BroadcastEcho:
    """A broadcast command passed back round the chain (``88 01 00 01 FF`` for IF_Clear)."""

    message: bytes

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.message


Reply: TypeAlias = (
    Ack | Completion | ErrorReply | InquiryReply | NetworkChange | AddressSetReply | BroadcastEcho
)


def decode_reply(packet: Packet) -> Reply:
    """Classify a packet received by the controller; raise CodecError if it is none of them."""
    msg = packet.message
    if packet.receiver == BROADCAST_ADDRESS:
        if len(msg) == 2 and msg[0] == 0x30:
            return AddressSetReply(next_address=msg[1])
        return BroadcastEcho(message=msg)
    kind, low = msg[0] & 0xF0, msg[0] & 0x0F
    if msg == b"\x38":
        return NetworkChange()
    if kind == 0x40 and len(msg) == 1 and low in SOCKETS:
        return Ack(socket=low)
    if kind == 0x50 and low == 0:
        return InquiryReply(data=msg[1:])
    if kind == 0x50 and len(msg) == 1 and low in SOCKETS:
        return Completion(socket=low)
    if kind == 0x60 and len(msg) == 2:
        return ErrorReply(socket=low, code=msg[1])
    raise CodecError(f"unrecognised reply {packet.to_bytes().hex(' ')}")


# --------------------------------------------------------------------------------------------
# Inquiry reply payloads
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FocusPosition:
    """Focus motor position in counts."""

    counts: int

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return encode_u16(self.counts, "focus counts")

    @classmethod
    def from_data(cls, data: bytes) -> FocusPosition:
        """Parse inquiry-reply data."""
        return cls(decode_u16(_expect_len(data, 4, "focus position")))


@dataclass(frozen=True, slots=True)
class ZoomPosition:
    """Zoom motor position in counts."""

    counts: int

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return encode_u16(self.counts, "zoom counts")

    @classmethod
    def from_data(cls, data: bytes) -> ZoomPosition:
        """Parse inquiry-reply data."""
        return cls(decode_u16(_expect_len(data, 4, "zoom position")))


@dataclass(frozen=True, slots=True)
class FocusModeState:
    """Whether autofocus is on."""

    auto: bool

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return bytes((0x02 if self.auto else 0x03,))

    @classmethod
    def from_data(cls, data: bytes) -> FocusModeState:
        """Parse inquiry-reply data."""
        value = _expect_len(data, 1, "focus mode")[0]
        if value not in (0x02, 0x03):
            raise CodecError(f"focus mode value 0x{value:02X} is neither 02 (auto) nor 03 (manual)")
        return cls(auto=value == 0x02)


@dataclass(frozen=True, slots=True)
class PowerState:
    """Whether the camera is powered on (not in standby)."""

    on: bool

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return bytes((0x02 if self.on else 0x03,))

    @classmethod
    def from_data(cls, data: bytes) -> PowerState:
        """Parse inquiry-reply data."""
        value = _expect_len(data, 1, "power")[0]
        # Some models report 04 for a power fault; treat anything but 02 as not on.
        return cls(on=value == 0x02)


@dataclass(frozen=True, slots=True)
class PanTiltPosition:
    """Pan and tilt positions in raw signed counts."""

    pan: int
    tilt: int

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return encode_s16(self.pan, "pan position") + encode_s16(self.tilt, "tilt position")

    @classmethod
    def from_data(cls, data: bytes) -> PanTiltPosition:
        """Parse inquiry-reply data."""
        _expect_len(data, 8, "pan/tilt position")
        return cls(pan=decode_s16(data[:4]), tilt=decode_s16(data[4:]))


@dataclass(frozen=True, slots=True)
class PanTiltMaxSpeed:
    """Maximum pan and tilt speed codes."""

    pan_speed: int
    tilt_speed: int

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        check_range("max pan speed", self.pan_speed, 1, 0x7F)
        check_range("max tilt speed", self.tilt_speed, 1, 0x7F)
        return bytes((self.pan_speed, self.tilt_speed))

    @classmethod
    def from_data(cls, data: bytes) -> PanTiltMaxSpeed:
        """Parse inquiry-reply data."""
        _expect_len(data, 2, "pan/tilt max speed")
        return cls(pan_speed=data[0], tilt_speed=data[1])


@dataclass(frozen=True, slots=True)
class Version:
    """VersionInq answer: vendor, model, ROM version, and the number of command sockets."""

    vendor: int
    model: int
    rom: int
    max_sockets: int

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        # GG GG HH HH JJ JJ are plain bytes; keep each below 0x80 so no header or FF appears.
        out = bytearray()
        for name, value in (("vendor", self.vendor), ("model", self.model), ("rom", self.rom)):
            check_range(name, value, 0, 0x7F7F)
            if value & 0x80:
                raise ValueError(f"{name} = 0x{value:04X}: each byte must be below 0x80")
            out += bytes((value >> 8, value & 0xFF))
        out.append(check_range("max sockets", self.max_sockets, 0, 0x0F))
        return bytes(out)

    @classmethod
    def from_data(cls, data: bytes) -> Version:
        """Parse inquiry-reply data."""
        _expect_len(data, 7, "version")
        return cls(
            vendor=(data[0] << 8) | data[1],
            model=(data[2] << 8) | data[3],
            rom=(data[4] << 8) | data[5],
            max_sockets=data[6],
        )


@dataclass(frozen=True, slots=True)
class Acknowledged:
    """Empty inquiry-class reply (``z0 50 FF``), e.g. to a per-camera IF_Clear."""

    def to_data(self) -> bytes:
        """Inquiry-reply data bytes."""
        return b""

    @classmethod
    def from_data(cls, data: bytes) -> Acknowledged:
        """Parse inquiry-reply data."""
        _expect_len(data, 0, "IF_Clear reply")
        return cls()


InquiryData: TypeAlias = (
    FocusPosition
    | ZoomPosition
    | FocusModeState
    | PowerState
    | PanTiltPosition
    | PanTiltMaxSpeed
    | Version
    | Acknowledged
)


def _expect_len(data: bytes, length: int, what: str) -> bytes:
    if len(data) != length:
        raise CodecError(f"{what} reply has {len(data)} data bytes, expected {length}")
    return data


# --------------------------------------------------------------------------------------------
# Requests (controller → camera)
# --------------------------------------------------------------------------------------------

RequestKind = Literal["command", "inquiry", "broadcast", "cancel"]


class PanDirection(enum.IntEnum):
    """Pan-tiltDrive XX byte."""

    LEFT = 0x01
    RIGHT = 0x02
    STOP = 0x03


class TiltDirection(enum.IntEnum):
    """Pan-tiltDrive YY byte."""

    UP = 0x01
    DOWN = 0x02
    STOP = 0x03


class FocusDirection(enum.IntEnum):
    """Focus drive direction (standard speed codes 00/02/03; variable 2p/3p)."""

    STOP = 0x00
    FAR = 0x02
    NEAR = 0x03


ReplyT = TypeVar("ReplyT", bound="InquiryData")


@dataclass(frozen=True, slots=True)
class _Fixed:
    """A request without arguments: its bytes are its PREFIX."""

    PREFIX: ClassVar[bytes] = b""
    KIND: ClassVar[RequestKind] = "command"

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX

    @classmethod
    def from_args(cls, args: bytes) -> Self:
        """Parse the bytes after PREFIX (there must be none)."""
        _expect_len(args, 0, cls.__name__)
        return cls()


@dataclass(frozen=True, slots=True)
class _Inquiry(_Fixed, Generic[ReplyT]):
    """An inquiry: answered ``z0 50 <data> FF`` without ACK, in the order asked."""

    KIND: ClassVar[RequestKind] = "inquiry"
    REPLY: ClassVar[type[InquiryData]]

    def parse_reply(self, data: bytes) -> ReplyT:
        """Decode the data bytes of the reply into this inquiry's typed answer."""
        return cast(ReplyT, self.REPLY.from_data(data))


@dataclass(frozen=True, slots=True)
class CamPower:
    """CAM_Power on (02) or standby (03)."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x00"
    KIND: ClassVar[RequestKind] = "command"
    on: bool

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX + (b"\x02" if self.on else b"\x03")

    @classmethod
    def from_args(cls, args: bytes) -> CamPower:
        """Parse the bytes after PREFIX."""
        return cls(on=_choice(args, {0x02: True, 0x03: False}, "power"))


@dataclass(frozen=True, slots=True)
class FocusDrive:
    """Focus Stop/Far/Near; ``speed`` 0–7 selects the variable-speed form (``2p``/``3p``)."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x08"
    KIND: ClassVar[RequestKind] = "command"
    direction: FocusDirection
    speed: int | None = None

    def __post_init__(self) -> None:
        if self.speed is not None:
            check_range("focus speed", self.speed, *FOCUS_SPEED_RANGE)
            if self.direction is FocusDirection.STOP:
                raise ValueError("focus speed is meaningless with Focus Stop; pass speed=None")

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        if self.speed is None:
            return self.PREFIX + bytes((int(self.direction),))
        return self.PREFIX + bytes(((int(self.direction) << 4) | self.speed,))

    @classmethod
    def from_args(cls, args: bytes) -> FocusDrive:
        """Parse the bytes after PREFIX."""
        value = _single(args, "focus drive")
        if value in (0x00, 0x02, 0x03):
            return cls(FocusDirection(value))
        if value >> 4 in (0x2, 0x3) and value & 0x0F <= FOCUS_SPEED_RANGE[1]:
            return cls(FocusDirection(value >> 4), speed=value & 0x0F)
        raise CodecError(f"focus drive byte 0x{value:02X} is not 00, 02, 03, 2p or 3p")


@dataclass(frozen=True, slots=True)
class FocusDirect:
    """Focus Direct to ``counts``."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x48"
    KIND: ClassVar[RequestKind] = "command"
    counts: int

    def __post_init__(self) -> None:
        check_range("focus counts", self.counts, 0, 0xFFFF)

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX + encode_u16(self.counts, "focus counts")

    @classmethod
    def from_args(cls, args: bytes) -> FocusDirect:
        """Parse the bytes after PREFIX."""
        return cls(decode_u16(args))


@dataclass(frozen=True, slots=True)
class FocusMode:
    """Focus Auto (02) or Manual (03)."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x38"
    KIND: ClassVar[RequestKind] = "command"
    auto: bool

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX + (b"\x02" if self.auto else b"\x03")

    @classmethod
    def from_args(cls, args: bytes) -> FocusMode:
        """Parse the bytes after PREFIX."""
        return cls(auto=_choice(args, {0x02: True, 0x03: False}, "focus mode"))


@dataclass(frozen=True, slots=True)
class FocusOnePush(_Fixed):
    """One Push AF trigger."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x18\x01"
    KIND: ClassVar[RequestKind] = "command"


@dataclass(frozen=True, slots=True)
class ZoomDirect:
    """Zoom Direct to ``counts``."""

    PREFIX: ClassVar[bytes] = b"\x01\x04\x47"
    KIND: ClassVar[RequestKind] = "command"
    counts: int

    def __post_init__(self) -> None:
        check_range("zoom counts", self.counts, 0, 0xFFFF)

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX + encode_u16(self.counts, "zoom counts")

    @classmethod
    def from_args(cls, args: bytes) -> ZoomDirect:
        """Parse the bytes after PREFIX."""
        return cls(decode_u16(args))


@dataclass(frozen=True, slots=True)
class PanTiltDrive:
    """Pan-tiltDrive: continuous motion at speed codes (speed 00 is never sent)."""

    PREFIX: ClassVar[bytes] = b"\x01\x06\x01"
    KIND: ClassVar[RequestKind] = "command"
    pan_speed: int
    tilt_speed: int
    pan: PanDirection
    tilt: TiltDirection

    def __post_init__(self) -> None:
        check_range("pan speed", self.pan_speed, *PAN_SPEED_RANGE)
        check_range("tilt speed", self.tilt_speed, *TILT_SPEED_RANGE)

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return self.PREFIX + bytes((self.pan_speed, self.tilt_speed, self.pan, self.tilt))

    @classmethod
    def from_args(cls, args: bytes) -> PanTiltDrive:
        """Parse the bytes after PREFIX."""
        _expect_len(args, 4, "pan-tilt drive")
        try:
            pan, tilt = PanDirection(args[2]), TiltDirection(args[3])
            return cls(args[0], args[1], pan, tilt)
        except ValueError as exc:
            raise CodecError(f"pan-tilt drive: {exc}") from exc

    @classmethod
    def stop(cls, pan_speed: int = 1, tilt_speed: int = 1) -> PanTiltDrive:
        """The Pan-tiltDrive Stop command (speeds ≥ 01: some models reject 00)."""
        return cls(pan_speed, tilt_speed, PanDirection.STOP, TiltDirection.STOP)


@dataclass(frozen=True, slots=True)
class _PanTiltMove:
    """Absolute/relative pan-tilt move: speed codes and raw signed positions."""

    PREFIX: ClassVar[bytes] = b""
    KIND: ClassVar[RequestKind] = "command"
    pan_speed: int
    tilt_speed: int
    pan: int
    tilt: int

    def __post_init__(self) -> None:
        check_range("pan speed", self.pan_speed, *PAN_SPEED_RANGE)
        check_range("tilt speed", self.tilt_speed, *TILT_SPEED_RANGE)
        check_range("pan position", self.pan, -0x8000, 0x7FFF)
        check_range("tilt position", self.tilt, -0x8000, 0x7FFF)

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return (
            self.PREFIX
            + bytes((self.pan_speed, self.tilt_speed))
            + encode_s16(self.pan, "pan position")
            + encode_s16(self.tilt, "tilt position")
        )

    @classmethod
    def from_args(cls, args: bytes) -> Self:
        """Parse the bytes after PREFIX."""
        _expect_len(args, 10, "pan-tilt position command")
        return cls(args[0], args[1], decode_s16(args[2:6]), decode_s16(args[6:10]))


@dataclass(frozen=True, slots=True)
class PanTiltAbsolute(_PanTiltMove):
    """Absolute pan/tilt move to raw signed positions at speed codes."""

    PREFIX: ClassVar[bytes] = b"\x01\x06\x02"


@dataclass(frozen=True, slots=True)
class PanTiltRelative(_PanTiltMove):
    """Relative pan/tilt move by raw signed counts at speed codes."""

    PREFIX: ClassVar[bytes] = b"\x01\x06\x03"


@dataclass(frozen=True, slots=True)
class PanTiltHome(_Fixed):
    """Move pan/tilt to the home (centre) position."""

    PREFIX: ClassVar[bytes] = b"\x01\x06\x04"
    KIND: ClassVar[RequestKind] = "command"


@dataclass(frozen=True, slots=True)
class PanTiltReset(_Fixed):
    """Re-initialise the pan/tilt mechanics (runs to the end stops, then home)."""

    PREFIX: ClassVar[bytes] = b"\x01\x06\x05"
    KIND: ClassVar[RequestKind] = "command"


@dataclass(frozen=True, slots=True)
class AddressSet(_Fixed):
    """Address Set broadcast: the first camera takes address 1, the next 2, …"""

    PREFIX: ClassVar[bytes] = b"\x30\x01"
    KIND: ClassVar[RequestKind] = "broadcast"


@dataclass(frozen=True, slots=True)
class IFClearBroadcast(_Fixed):
    """IF_Clear to every camera on the chain (header 88); the chain echoes it back."""

    PREFIX: ClassVar[bytes] = b"\x01\x00\x01"
    KIND: ClassVar[RequestKind] = "broadcast"


@dataclass(frozen=True, slots=True)
class Cancel:
    """Cancel the command running in ``socket``."""

    PREFIX: ClassVar[bytes] = b""
    KIND: ClassVar[RequestKind] = "cancel"
    socket: int

    def __post_init__(self) -> None:
        check_range("socket", self.socket, 1, 2)

    def to_message(self) -> bytes:
        """Message bytes (without header and terminator)."""
        return bytes((0x20 | self.socket,))

    @classmethod
    def from_args(cls, args: bytes) -> Cancel:
        """Parse the whole message (``2p``)."""
        value = _single(args, "cancel")
        if value >> 4 != 0x2 or value & 0x0F not in SOCKETS:
            raise CodecError(f"cancel byte 0x{value:02X} is not 21 or 22")
        return cls(value & 0x0F)


@dataclass(frozen=True, slots=True)
class IFClear(_Inquiry[Acknowledged]):
    """IF_Clear to one camera: clears its command buffers; answered ``z0 50 FF`` (no socket)."""

    PREFIX: ClassVar[bytes] = b"\x01\x00\x01"
    REPLY: ClassVar[type[InquiryData]] = Acknowledged


@dataclass(frozen=True, slots=True)
class FocusPositionInquiry(_Inquiry[FocusPosition]):
    """FocusPosInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x04\x48"
    REPLY: ClassVar[type[InquiryData]] = FocusPosition


@dataclass(frozen=True, slots=True)
class ZoomPositionInquiry(_Inquiry[ZoomPosition]):
    """ZoomPosInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x04\x47"
    REPLY: ClassVar[type[InquiryData]] = ZoomPosition


@dataclass(frozen=True, slots=True)
class FocusModeInquiry(_Inquiry[FocusModeState]):
    """FocusModeInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x04\x38"
    REPLY: ClassVar[type[InquiryData]] = FocusModeState


@dataclass(frozen=True, slots=True)
class PowerInquiry(_Inquiry[PowerState]):
    """PowerInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x04\x00"
    REPLY: ClassVar[type[InquiryData]] = PowerState


@dataclass(frozen=True, slots=True)
class PanTiltPositionInquiry(_Inquiry[PanTiltPosition]):
    """Pan-tiltPosInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x06\x12"
    REPLY: ClassVar[type[InquiryData]] = PanTiltPosition


@dataclass(frozen=True, slots=True)
class PanTiltMaxSpeedInquiry(_Inquiry[PanTiltMaxSpeed]):
    """Pan-tiltMaxSpeedInq."""

    PREFIX: ClassVar[bytes] = b"\x09\x06\x11"
    REPLY: ClassVar[type[InquiryData]] = PanTiltMaxSpeed


@dataclass(frozen=True, slots=True)
class VersionInquiry(_Inquiry[Version]):
    """VersionInq (CAM_VersionInq)."""

    PREFIX: ClassVar[bytes] = b"\x09\x00\x02"
    REPLY: ClassVar[type[InquiryData]] = Version


Command: TypeAlias = (
    CamPower
    | FocusDrive
    | FocusDirect
    | FocusMode
    | FocusOnePush
    | ZoomDirect
    | PanTiltDrive
    | PanTiltAbsolute
    | PanTiltRelative
    | PanTiltHome
    | PanTiltReset
)
Inquiry: TypeAlias = (
    IFClear
    | FocusPositionInquiry
    | ZoomPositionInquiry
    | FocusModeInquiry
    | PowerInquiry
    | PanTiltPositionInquiry
    | PanTiltMaxSpeedInquiry
    | VersionInquiry
)
Broadcast: TypeAlias = AddressSet | IFClearBroadcast
Request: TypeAlias = Command | Inquiry | Broadcast | Cancel

COMMAND_TYPES: tuple[type[Command], ...] = (
    CamPower, FocusDrive, FocusDirect, FocusMode, FocusOnePush, ZoomDirect,
    PanTiltDrive, PanTiltAbsolute, PanTiltRelative, PanTiltHome, PanTiltReset,
)  # fmt: skip
INQUIRY_TYPES: tuple[type[Inquiry], ...] = (
    IFClear, FocusPositionInquiry, ZoomPositionInquiry, FocusModeInquiry, PowerInquiry,
    PanTiltPositionInquiry, PanTiltMaxSpeedInquiry, VersionInquiry,
)  # fmt: skip
BROADCAST_TYPES: tuple[type[Broadcast], ...] = (AddressSet, IFClearBroadcast)


def encode_request(request: Request, camera_address: int) -> bytes:
    """Frame ``request`` for the camera at ``camera_address`` (broadcasts go to ``88``)."""
    if request.KIND == "broadcast":
        return Packet(CONTROLLER_ADDRESS, BROADCAST_ADDRESS, request.to_message()).to_bytes()
    check_range("camera address", camera_address, MIN_CAMERA_ADDRESS, MAX_CAMERA_ADDRESS)
    return Packet(CONTROLLER_ADDRESS, camera_address, request.to_message()).to_bytes()


def decode_request(packet: Packet) -> Request:
    """Device side: parse a packet sent by the controller; CodecError for a syntax error."""
    msg = packet.message
    if packet.receiver == BROADCAST_ADDRESS:
        candidates: tuple[type[Request], ...] = BROADCAST_TYPES
    elif len(msg) == 1 and msg[0] >> 4 == 0x2:
        return Cancel.from_args(msg)
    elif msg.startswith(IFClear.PREFIX):
        candidates = (IFClear,)
    elif msg[:1] == b"\x09":
        candidates = INQUIRY_TYPES
    else:
        candidates = COMMAND_TYPES
    for request_type in candidates:
        prefix = request_type.PREFIX
        if msg.startswith(prefix):
            try:
                return request_type.from_args(msg[len(prefix) :])
            except ValueError as exc:  # CodecError or an out-of-range argument
                raise CodecError(f"{request_type.__name__}: {exc}") from exc
    raise CodecError(f"unknown request {msg.hex(' ')}")


def encode_reply(reply: Reply, camera_address: int) -> bytes:
    """Device side: frame ``reply`` from the camera at ``camera_address``."""
    if isinstance(reply, AddressSetReply | BroadcastEcho):
        return Packet(CONTROLLER_ADDRESS, BROADCAST_ADDRESS, reply.to_message()).to_bytes()
    check_range("camera address", camera_address, MIN_CAMERA_ADDRESS, MAX_CAMERA_ADDRESS)
    return Packet(camera_address, CONTROLLER_ADDRESS, reply.to_message()).to_bytes()


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _single(args: bytes, what: str) -> int:
    return _expect_len(args, 1, what)[0]


def _choice(args: bytes, options: dict[int, bool], what: str) -> bool:
    value = _single(args, what)
    if value not in options:
        allowed = ", ".join(f"{k:02X}" for k in options)
        raise CodecError(f"{what} byte 0x{value:02X} is not one of {allowed}")
    return options[value]
