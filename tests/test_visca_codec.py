"""VISCA codec: property round trips of every request, reply and inquiry payload; reassembly."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.visca import codec, codec_framing, codec_replies, codec_requests

# ---- strategies -----------------------------------------------------------------------------

u16 = st.integers(0, 0xFFFF)
s16 = st.integers(-0x8000, 0x7FFF)
pan_speed = st.integers(*codec_requests.PAN_SPEED_RANGE)
tilt_speed = st.integers(*codec_requests.TILT_SPEED_RANGE)
address = st.integers(codec_framing.MIN_CAMERA_ADDRESS, codec_framing.MAX_CAMERA_ADDRESS)

commands: st.SearchStrategy[codec_requests.Request] = st.one_of(
    st.builds(codec_requests.CamPower, on=st.booleans()),
    st.builds(codec_requests.FocusDrive, st.sampled_from(list(codec_requests.FocusDirection))),
    st.builds(
        codec_requests.FocusDrive,
        st.sampled_from([codec_requests.FocusDirection.FAR, codec_requests.FocusDirection.NEAR]),
        st.integers(*codec_requests.FOCUS_SPEED_RANGE),
    ),
    st.builds(codec_requests.FocusDirect, u16),
    st.builds(codec_requests.FocusMode, auto=st.booleans()),
    st.just(codec_requests.FocusOnePush()),
    st.builds(codec_requests.ZoomDirect, u16),
    st.builds(
        codec_requests.PanTiltDrive,
        pan_speed,
        tilt_speed,
        st.sampled_from(list(codec_requests.PanDirection)),
        st.sampled_from(list(codec_requests.TiltDirection)),
    ),
    st.builds(codec_requests.PanTiltAbsolute, pan_speed, tilt_speed, s16, s16),
    st.builds(codec_requests.PanTiltRelative, pan_speed, tilt_speed, s16, s16),
    st.just(codec_requests.PanTiltHome()),
    st.just(codec_requests.PanTiltReset()),
    st.builds(codec_requests.Cancel, st.integers(1, 2)),
)
inquiries: st.SearchStrategy[codec_requests.Request] = st.sampled_from(
    [t() for t in codec_requests.INQUIRY_TYPES]
)
broadcasts: st.SearchStrategy[codec_requests.Request] = st.sampled_from(
    [t() for t in codec_requests.BROADCAST_TYPES]
)
version_word = st.integers(0, 0x7F).flatmap(
    lambda hi: st.integers(0, 0x7F).map(lambda lo: hi << 8 | lo)
)
payloads: st.SearchStrategy[codec_replies.InquiryData] = st.one_of(
    st.builds(codec_replies.FocusPosition, u16),
    st.builds(codec_replies.ZoomPosition, u16),
    st.builds(codec_replies.FocusModeState, auto=st.booleans()),
    st.builds(codec_replies.PowerState, on=st.booleans()),
    st.builds(codec_replies.PanTiltPosition, s16, s16),
    st.builds(codec_replies.PanTiltMaxSpeed, st.integers(1, 0x7F), st.integers(1, 0x7F)),
    st.builds(
        codec_replies.Version, version_word, version_word, version_word, st.integers(0, 0x0F)
    ),
    st.just(codec_replies.Acknowledged()),
)
non_ff = st.integers(0, 0xFE)
replies: st.SearchStrategy[codec_replies.Reply] = st.one_of(
    st.builds(codec_replies.Ack, st.integers(1, 2)),
    st.builds(codec_replies.Completion, st.integers(1, 2)),
    st.builds(codec_replies.ErrorReply, st.integers(0, 0x0F), st.integers(0, 0x7F)),
    st.builds(
        codec_replies.InquiryReply,
        st.binary(max_size=13).map(lambda b: b.replace(b"\xff", b"\x0f")),
    ),
    st.just(codec_replies.NetworkChange()),
    st.builds(codec_replies.AddressSetReply, st.integers(1, 8)),
    st.just(codec_replies.BroadcastEcho(codec_requests.IFClearBroadcast().to_message())),
)
# Message bytes of every VISCA message we use are below 0x80 (nibbles and small codes); a byte
# with the high bit set inside a packet can only be a header, so the reassembler restarts there.
packets = st.builds(
    lambda header, body: bytes([header, *body, 0xFF]),
    st.integers(0x80, 0xFE),
    st.lists(st.integers(0x00, 0x7F), min_size=1, max_size=14),
)

# ---- requests -------------------------------------------------------------------------------


@given(commands | inquiries | broadcasts, address)
def test_every_request_round_trips(request: codec_requests.Request, addr: int) -> None:
    wire = codec.encode_request(request, addr)
    assert codec_framing.MIN_PACKET_LEN <= len(wire) <= codec_framing.MAX_PACKET_LEN
    assert wire[-1] == 0xFF
    assert 0xFF not in wire[:-1]
    packet = codec_framing.Packet.from_bytes(wire)
    assert packet.to_bytes() == wire
    assert codec.decode_request(packet) == request


def test_request_bytes_match_design_table() -> None:
    assert codec.encode_request(codec_requests.FocusDirect(0x1234), 1) == bytes.fromhex(
        "81 01 04 48 01 02 03 04 FF"
    )
    assert codec.encode_request(codec_requests.PanTiltDrive.stop(), 2) == bytes.fromhex(
        "82 01 06 01 01 01 03 03 FF"
    )
    assert codec.encode_request(
        codec_requests.PanTiltAbsolute(0x18, 0x14, -1, 0x168), 1
    ) == bytes.fromhex("81 01 06 02 18 14 0F 0F 0F 0F 00 01 06 08 FF")
    assert codec.encode_request(codec_requests.AddressSet(), 3) == bytes.fromhex("88 30 01 FF")
    assert codec.encode_request(codec_requests.Cancel(2), 1) == bytes.fromhex("81 22 FF")
    assert codec.encode_request(codec_requests.VersionInquiry(), 7) == bytes.fromhex(
        "87 09 00 02 FF"
    )


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: codec_requests.FocusDirect(-1), "focus counts"),
        (lambda: codec_requests.FocusDirect(0x10000), "focus counts"),
        (
            lambda: codec_requests.PanTiltDrive(
                0, 1, codec_requests.PanDirection.LEFT, codec_requests.TiltDirection.UP
            ),
            "pan speed",
        ),
        (lambda: codec_requests.PanTiltAbsolute(1, 0x18, 0, 0), "tilt speed"),
        (lambda: codec_requests.PanTiltAbsolute(1, 1, 0x8000, 0), "pan position"),
        (lambda: codec_requests.FocusDrive(codec_requests.FocusDirection.FAR, 8), "focus speed"),
        (lambda: codec_requests.Cancel(3), "socket"),
        (lambda: codec.encode_request(codec_requests.PanTiltHome(), 8), "camera address"),
    ],
)
def test_out_of_range_arguments_name_the_field(make: object, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        make()  # type: ignore[operator]


def test_malformed_requests_are_codec_errors() -> None:
    for raw in (
        "81 01 04 48 01 02 03 FF",
        "81 01 06 01 00 01 03 03 FF",
        "81 09 09 09 FF",
        "81 2F FF",
    ):
        with pytest.raises(codec_framing.CodecError):
            codec.decode_request(codec_framing.Packet.from_bytes(bytes.fromhex(raw)))


# ---- values ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "wire"),
    [(-1, "0F 0F 0F 0F"), (-32768, "08 00 00 00"), (32767, "07 0F 0F 0F"), (0, "00 00 00 00")],
)
def test_signed_edges(value: int, wire: str) -> None:
    assert codec_framing.encode_s16(value) == bytes.fromhex(wire)
    assert codec_framing.decode_s16(bytes.fromhex(wire)) == value


@given(s16)
def test_signed_round_trip(value: int) -> None:
    encoded = codec_framing.encode_s16(value)
    assert all(b <= 0x0F for b in encoded)
    assert codec_framing.decode_s16(encoded) == value


def test_signed_out_of_range_raises() -> None:
    for value in (-32769, 32768):
        with pytest.raises(ValueError, match="pan"):
            codec_framing.encode_s16(value, "pan")


# ---- replies and inquiry payloads -------------------------------------------------------------


@given(replies, address)
def test_every_reply_round_trips(reply: codec_replies.Reply, addr: int) -> None:
    wire = codec.encode_reply(reply, addr)
    packet = codec_framing.Packet.from_bytes(wire)
    assert codec.decode_reply(packet) == reply
    if not isinstance(reply, codec_replies.AddressSetReply | codec_replies.BroadcastEcho):
        assert wire[0] == codec_framing.reply_header(addr)
        assert packet.sender == addr


@given(payloads, address)
def test_every_inquiry_payload_round_trips_through_a_reply_packet(
    payload: codec_replies.InquiryData, addr: int
) -> None:
    inquiry = next(t() for t in codec_requests.INQUIRY_TYPES if t.REPLY is type(payload))
    wire = codec.encode_reply(codec_replies.InquiryReply(payload.to_data()), addr)
    reply = codec.decode_reply(codec_framing.Packet.from_bytes(wire))
    assert isinstance(reply, codec_replies.InquiryReply)
    assert inquiry.parse_reply(reply.data) == payload


def test_reply_bytes_match_design_table() -> None:
    decode = lambda raw: codec.decode_reply(codec_framing.Packet.from_bytes(bytes.fromhex(raw)))  # noqa: E731
    assert decode("90 41 FF") == codec_replies.Ack(1)
    assert decode("90 52 FF") == codec_replies.Completion(2)
    assert decode("90 61 41 FF") == codec_replies.ErrorReply(
        1, codec_replies.ErrorCode.NOT_EXECUTABLE
    )
    assert decode("90 60 03 FF") == codec_replies.ErrorReply(0, codec_replies.ErrorCode.BUFFER_FULL)
    assert decode("90 38 FF") == codec_replies.NetworkChange()
    assert decode("88 30 02 FF") == codec_replies.AddressSetReply(2)
    assert decode("90 50 FF") == codec_replies.InquiryReply(b"")
    pan_tilt = codec_requests.PanTiltPositionInquiry().parse_reply(
        bytes.fromhex("0F 0A 06 00 00 01 06 08")
    )
    assert pan_tilt == codec_replies.PanTiltPosition(pan=-0x5A0, tilt=0x168)


def test_inquiry_reply_of_wrong_length_is_rejected() -> None:
    with pytest.raises(codec_framing.CodecError):
        codec_requests.FocusPositionInquiry().parse_reply(b"\x01\x02\x03")
    with pytest.raises(codec_framing.CodecError):
        codec_requests.FocusModeInquiry().parse_reply(b"\x07")


# ---- reassembler ------------------------------------------------------------------------------


@given(st.lists(packets, max_size=20))
def test_reassembler_whole_and_byte_by_byte(pkts: list[bytes]) -> None:
    stream = b"".join(pkts)
    assert codec_framing.Reassembler().feed(stream) == pkts
    one = codec_framing.Reassembler()
    out: list[bytes] = []
    for byte in stream:
        out += one.feed(bytes([byte]))
    assert out == pkts
    assert one.pending == 0
    assert one.dropped_bytes == 0


@given(st.lists(packets, max_size=10), st.data())
def test_reassembler_random_chunks(pkts: list[bytes], data: st.DataObject) -> None:
    stream = b"".join(pkts)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    reassembler = codec_framing.Reassembler()
    out: list[bytes] = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        out += reassembler.feed(stream[start:end])
    assert out == pkts


@given(st.lists(st.tuples(st.binary(max_size=12), packets), max_size=10))
def test_reassembler_low_junk_between_packets_is_dropped(
    items: list[tuple[bytes, bytes]],
) -> None:
    # Junk without the high bit set can never start a packet: every packet survives intact.
    reassembler = codec_framing.Reassembler()
    stream = b"".join(bytes(b & 0x7F for b in junk) + pkt for junk, pkt in items)
    assert reassembler.feed(stream) == [pkt for _, pkt in items]
    assert reassembler.dropped_bytes == sum(len(junk) for junk, _ in items)


@given(st.lists(st.tuples(st.binary(max_size=40), packets), max_size=8))
def test_reassembler_resynchronises_after_any_junk_ending_in_ff(
    items: list[tuple[bytes, bytes]],
) -> None:
    # Arbitrary junk (it may look like packets, or run past 16 bytes) followed by FF leaves the
    # reassembler in sync: the next real packet comes out intact, in order.
    reassembler = codec_framing.Reassembler()
    out: list[bytes] = []
    for junk, pkt in items:
        out += reassembler.feed(junk + b"\xff" + pkt)
        assert out[-1] == pkt
    for raw in out:
        assert codec_framing.MIN_PACKET_LEN <= len(raw) <= codec_framing.MAX_PACKET_LEN
        assert raw[0] & 0x80
        assert raw[-1] == 0xFF
        assert 0xFF not in raw[:-1]


def test_reassembler_drops_overlong_run_and_short_runs() -> None:
    reassembler = codec_framing.Reassembler()
    overlong = b"\x90" + bytes(range(1, 31))  # 31 bytes, no terminator
    good = bytes.fromhex("90 41 FF")
    assert reassembler.feed(overlong + b"\xff" + good) == [good]
    assert reassembler.dropped_bytes == len(overlong) + 1
    assert reassembler.feed(bytes.fromhex("90 FF FF 90 51 FF")) == [bytes.fromhex("90 51 FF")]
    assert reassembler.feed(b"\x90\x50") == []
    assert reassembler.pending == 2
    assert reassembler.clear() == 2
    assert reassembler.pending == 0


@settings(max_examples=200)
@given(st.binary(max_size=200))
def test_reassembler_never_fails_and_emits_only_framed_packets(stream: bytes) -> None:
    reassembler = codec_framing.Reassembler()
    out = reassembler.feed(stream)
    assert reassembler.pending <= codec_framing.MAX_PACKET_LEN
    for raw in out:
        assert codec_framing.MIN_PACKET_LEN <= len(raw) <= codec_framing.MAX_PACKET_LEN
        assert raw[-1] == 0xFF
    assert sum(map(len, out)) + reassembler.dropped_bytes + reassembler.pending == len(stream)


def test_reassembler_restarts_at_a_header_when_a_terminator_was_lost() -> None:
    reassembler = codec_framing.Reassembler()
    # "90 41" lost its FF on the wire; the Completion that follows must still come out whole.
    assert reassembler.feed(b"\x90\x41\x90\x51\xff") == [b"\x90\x51\xff"]
    assert reassembler.dropped_bytes == 2
