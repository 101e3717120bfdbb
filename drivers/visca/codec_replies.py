"""VISCA replies (camera → controller) and the typed data inquiry replies carry.

The reply messages (:class:`Ack`, :class:`Completion`, :class:`ErrorReply` with its
:class:`ErrorCode`, :class:`InquiryReply`, :class:`NetworkChange`, and the broadcasts' answers
:class:`AddressSetReply` and :class:`BroadcastEcho`: :data:`Reply`), and the payloads an
inquiry's reply decodes into (:class:`FocusPosition`, :class:`Version`, …: :data:`InquiryData`),
each with its bytes both ways. Frozen dataclasses, no I/O; the simulated camera encodes with them,
the session decodes. Split from :mod:`drivers.visca.codec`, whose :func:`decode_reply` classifies
a received packet into one of these.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TypeAlias

from drivers.visca.codec_framing import (
    CodecError,
    check_range,
    decode_s16,
    decode_u16,
    encode_s16,
    encode_u16,
    expect_len,
)

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
        return cls(decode_u16(expect_len(data, 4, "focus position")))


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
        return cls(decode_u16(expect_len(data, 4, "zoom position")))


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
        value = expect_len(data, 1, "focus mode")[0]
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
        value = expect_len(data, 1, "power")[0]
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
        expect_len(data, 8, "pan/tilt position")
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
        expect_len(data, 2, "pan/tilt max speed")
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
        expect_len(data, 7, "version")
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
        expect_len(data, 0, "IF_Clear reply")
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
