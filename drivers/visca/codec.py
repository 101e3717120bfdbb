"""Sans-IO VISCA codec: a typed request or reply ↔ a framed packet, in both directions.

Pure functions over frozen dataclasses; both the driver (controller side) and the simulated
camera (device side) use the codec, so a packet is encoded and decoded in exactly one place.

The codec is four modules (design.md §6): :mod:`drivers.visca.codec_framing` (the packet, the
reassembler, nibble-encoded values, addresses and :class:`CodecError`),
:mod:`drivers.visca.codec_requests` (controller → camera messages),
:mod:`drivers.visca.codec_replies` (camera → controller messages and the data inquiry replies
carry), and this one, which joins them: :func:`encode_request` and :func:`decode_reply` for the
controller, :func:`decode_request` and :func:`encode_reply` for the device. The other three were
split from this module, which held the whole codec.
"""

from __future__ import annotations

from drivers.visca.codec_framing import (
    BROADCAST_ADDRESS,
    CONTROLLER_ADDRESS,
    MAX_CAMERA_ADDRESS,
    MIN_CAMERA_ADDRESS,
    SOCKETS,
    CodecError,
    Packet,
    check_range,
)
from drivers.visca.codec_replies import (
    Ack,
    AddressSetReply,
    BroadcastEcho,
    Completion,
    ErrorReply,
    InquiryReply,
    NetworkChange,
    Reply,
)
from drivers.visca.codec_requests import (
    BROADCAST_TYPES,
    COMMAND_TYPES,
    INQUIRY_TYPES,
    Cancel,
    IFClear,
    Request,
)


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
