"""VISCA requests (controller → camera): commands, inquiries, broadcasts and Cancel.

One frozen dataclass per message the driver sends (design.md §6.3), each with its ``PREFIX``,
its ``KIND`` (``command``, ``inquiry``, ``broadcast`` or ``cancel``), ``to_message`` and
``from_args`` (the device side parses with it); an inquiry also names the data type of its reply
(``REPLY``, :mod:`drivers.visca.codec_replies`) and parses it. The unions :data:`Command`,
:data:`Inquiry`, :data:`Broadcast` and :data:`Request` and their type tuples are what the session
and the simulated device dispatch on. Split from :mod:`drivers.visca.codec`, whose
:func:`encode_request` and :func:`decode_request` frame and parse these.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import ClassVar, Generic, Literal, Self, TypeAlias, TypeVar, cast

from drivers.visca.codec_framing import (
    SOCKETS,
    CodecError,
    check_range,
    decode_s16,
    decode_u16,
    encode_s16,
    encode_u16,
    expect_len,
)
from drivers.visca.codec_replies import (
    Acknowledged,
    FocusModeState,
    FocusPosition,
    InquiryData,
    PanTiltMaxSpeed,
    PanTiltPosition,
    PowerState,
    Version,
    ZoomPosition,
)

# Speed ranges accepted by the wire format. Model profiles (profiles.py) narrow these further;
# 0x18 is the widest pan speed of the EVI family, 0x17 the widest tilt speed (EVI-D70).
PAN_SPEED_RANGE = (0x01, 0x18)
TILT_SPEED_RANGE = (0x01, 0x17)
FOCUS_SPEED_RANGE = (0, 7)


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
        expect_len(args, 0, cls.__name__)
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
        expect_len(args, 4, "pan-tilt drive")
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
        expect_len(args, 10, "pan-tilt position command")
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


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _single(args: bytes, what: str) -> int:
    return expect_len(args, 1, what)[0]


def _choice(args: bytes, options: dict[int, bool], what: str) -> bool:
    value = _single(args, what)
    if value not in options:
        allowed = ", ".join(f"{k:02X}" for k in options)
        raise CodecError(f"{what} byte 0x{value:02X} is not one of {allowed}")
    return options[value]
