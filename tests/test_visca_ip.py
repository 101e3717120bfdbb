"""VISCA over IP: the envelope codec, the controller's channel and the simulated camera's side."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig
from drivers.sim.ip_server import IpCameraEndpoint
from drivers.sim.state import CameraState
from drivers.visca.ip import (
    MAX_RETRANSMITS,
    RETRANSMIT_S,
    Datagram,
    IpChannel,
    IpFrameError,
    PayloadType,
    decode_datagram,
    encode_datagram,
)

PEER = ("127.0.0.1", 40000)
FOCUS_POS_INQ = bytes.fromhex("81090448ff")
FOCUS_DIRECT = bytes.fromhex("8101044803000000ff")


def test_headers_are_byte_exact() -> None:
    assert encode_datagram(PayloadType.COMMAND, 1, FOCUS_DIRECT) == bytes.fromhex(
        "0100 0009 00000001 8101044803000000ff"
    )
    assert encode_datagram(PayloadType.INQUIRY, 0xDEADBEEF, FOCUS_POS_INQ) == bytes.fromhex(
        "0110 0005 deadbeef 81090448ff"
    )
    assert encode_datagram(PayloadType.CONTROL, 0, b"\x01") == bytes.fromhex(
        "0200 0001 00000000 01"
    )
    assert decode_datagram(bytes.fromhex("0201 0002 00000007 0f01")) == Datagram(
        PayloadType.CONTROL_REPLY, 7, b"\x0f\x01"
    )
    assert decode_datagram(bytes.fromhex("0111 0003 00000002 9041ff")) == Datagram(
        PayloadType.REPLY, 2, b"\x90\x41\xff"
    )


@given(
    kind=st.sampled_from(list(PayloadType)) | st.integers(0, 0xFFFF),
    seq=st.integers(0, 2**32 - 1),
    payload=st.binary(min_size=1, max_size=16),
)
def test_datagrams_round_trip(kind: int, seq: int, payload: bytes) -> None:
    data = encode_datagram(kind, seq, payload)
    assert len(data) == 8 + len(payload)
    assert decode_datagram(data) == Datagram(kind, seq, payload)


@given(st.binary(max_size=40))
def test_decoding_garbage_raises_only_frame_errors(data: bytes) -> None:
    try:
        msg = decode_datagram(data)
    except IpFrameError:
        return
    assert msg.encode() == data


@pytest.mark.parametrize(
    ("kind", "seq", "payload"),
    [(0x10000, 0, b"\x01"), (0x0100, 2**32, b"\x01"), (0x0100, 0, b""), (0x0100, 0, bytes(17))],
)
def test_out_of_range_fields_are_refused(kind: int, seq: int, payload: bytes) -> None:
    with pytest.raises(ValueError):
        encode_datagram(kind, seq, payload)


def _reply(seq: int, hex_payload: str, kind: int = PayloadType.REPLY) -> bytes:
    return encode_datagram(kind, seq, bytes.fromhex(hex_payload))


def _connected() -> IpChannel:
    ch = IpChannel()
    ch.connection_made(0.0)
    [reset] = ch.datagrams_to_send()
    assert reset == bytes.fromhex("0200 0001 00000000 01")
    ch.receive(_reply(0, "01", PayloadType.CONTROL_REPLY), 0.0)
    return ch


def test_channel_sends_one_datagram_at_a_time_and_matches_by_sequence() -> None:
    ch = _connected()
    ch.send(FOCUS_DIRECT, 0.0)
    ch.send(FOCUS_POS_INQ, 0.0)
    [first] = ch.datagrams_to_send()
    assert decode_datagram(first) == Datagram(PayloadType.COMMAND, 1, FOCUS_DIRECT)
    ch.receive(_reply(1, "9041ff"), 0.01)
    assert ch.data_received() == bytes.fromhex("9041ff")
    [second] = ch.datagrams_to_send()
    assert decode_datagram(second) == Datagram(PayloadType.INQUIRY, 2, FOCUS_POS_INQ)
    ch.receive(_reply(1, "9041ff"), 0.02)  # duplicate ACK
    ch.receive(_reply(2, "905003000000ff"), 0.02)
    ch.receive(_reply(2, "905003000000ff"), 0.02)  # duplicate answer
    ch.receive(_reply(1, "9051ff"), 0.03)
    ch.receive(_reply(1, "9051ff"), 0.03)  # duplicate Completion
    assert ch.data_received() == bytes.fromhex("905003000000ff 9051ff")
    assert ch.stats.duplicates == 3


def test_timeout_resends_the_same_sequence_number_then_gives_up() -> None:
    ch = _connected()
    ch.send(FOCUS_DIRECT, 0.0)
    [first] = ch.datagrams_to_send()
    t = 0.0
    for _ in range(MAX_RETRANSMITS):
        t += RETRANSMIT_S
        ch.poll(t)
        assert ch.datagrams_to_send() == [first]
    ch.poll(t + RETRANSMIT_S)
    assert ch.datagrams_to_send() == []
    assert ch.next_deadline() is None
    assert ch.stats.given_up == 1


def test_lost_ack_is_restored_from_the_completion_after_a_sequence_error() -> None:
    ch = _connected()
    ch.send(FOCUS_DIRECT, 0.0)
    ch.send(FOCUS_POS_INQ, 0.0)
    ch.datagrams_to_send()
    ch.poll(RETRANSMIT_S)  # the ACK was lost: resend seq 1
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.07)  # "already performed"
    [inquiry] = ch.datagrams_to_send()
    assert decode_datagram(inquiry).seq == 2
    ch.receive(_reply(1, "9052ff"), 0.5)
    assert ch.data_received() == bytes.fromhex("9042ff 9052ff")
    assert ch.stats.acks_restored == 1


def test_inquiry_whose_reply_was_lost_is_asked_again_under_a_new_number() -> None:
    ch = _connected()
    ch.send(FOCUS_POS_INQ, 0.0)
    ch.datagrams_to_send()
    ch.poll(RETRANSMIT_S)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.07)
    [again] = ch.datagrams_to_send()
    assert decode_datagram(again) == Datagram(PayloadType.INQUIRY, 2, FOCUS_POS_INQ)
    ch.receive(_reply(1, "905003000000ff"), 0.08)  # the first answer was only late
    ch.receive(_reply(2, "905003000000ff"), 0.09)  # the session gets exactly one
    assert ch.data_received() == bytes.fromhex("905003000000ff")


def test_duplicate_refused_first_send_waits_for_the_real_reply() -> None:
    ch = _connected()
    ch.send(FOCUS_DIRECT, 0.0)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.005)
    ch.receive(_reply(1, "9041ff"), 0.017)
    ch.poll(RETRANSMIT_S)
    assert ch.datagrams_to_send() == []
    assert ch.data_received() == bytes.fromhex("9041ff")


def test_sequence_error_with_nothing_else_resets_then_resends() -> None:
    ch = _connected()
    ch.send(FOCUS_DIRECT, 0.0)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.01)
    assert ch.datagrams_to_send() == []  # a duplicate's refusal: the real reply may follow
    ch.poll(RETRANSMIT_S)
    [reset] = ch.datagrams_to_send()
    assert decode_datagram(reset) == Datagram(PayloadType.CONTROL, 0, b"\x01")
    ch.receive(_reply(0, "01", PayloadType.CONTROL_REPLY), 0.02)
    [again] = ch.datagrams_to_send()
    assert decode_datagram(again) == Datagram(PayloadType.COMMAND, 2, FOCUS_DIRECT)


def test_lax_camera_without_sequence_echo_and_inquiry_envelope_refusal() -> None:
    ch = _connected()
    ch.send(FOCUS_POS_INQ, 0.0)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f02", PayloadType.CONTROL_REPLY), 0.01)
    [again] = ch.datagrams_to_send()
    assert decode_datagram(again).kind == PayloadType.COMMAND
    ch.receive(_reply(0, "905003000000ff"), 0.02)  # answers with sequence number 0
    assert ch.data_received() == bytes.fromhex("905003000000ff")
    assert not ch.camera_echoes_seq
    assert ch.next_deadline() is None


def test_one_address_is_one_camera_address_set_and_if_clear() -> None:
    ch = _connected()
    ch.send(bytes.fromhex("883001ff"), 0.0)
    assert ch.data_received() == bytes.fromhex("883002ff")
    assert ch.datagrams_to_send() == []
    ch.send(bytes.fromhex("88010001ff"), 0.0)
    [clear] = ch.datagrams_to_send()
    assert decode_datagram(clear) == Datagram(PayloadType.COMMAND, 1, bytes.fromhex("81010001ff"))
    ch.receive(_reply(1, "9050ff"), 0.01)
    assert ch.data_received() == bytes.fromhex("88010001ff")


# ---- the camera's side ------------------------------------------------------------------------


def _camera() -> IpCameraEndpoint:
    state = CameraState(clock=lambda: 0.0)
    device = ViscaDevice(
        state, DeviceConfig(network_change_at_power_up=False, autofocus_at_power_up=False)
    )
    device.power_up(0.0)
    endpoint = IpCameraEndpoint(device)
    endpoint.poll(1.0)
    endpoint.datagrams_to_send()
    return endpoint


def _exchange(cam: IpCameraEndpoint, datagram: bytes, t: float) -> list[Datagram]:
    cam.receive(datagram, PEER, t)
    cam.poll(t + 0.1)
    return [decode_datagram(d) for d, peer in cam.datagrams_to_send() if peer == PEER]


def test_camera_answers_reset_and_echoes_sequence_numbers() -> None:
    cam = _camera()
    assert _exchange(cam, encode_datagram(PayloadType.CONTROL, 9, b"\x01"), 1.0) == [
        Datagram(PayloadType.CONTROL_REPLY, 9, b"\x01")
    ]
    replies = _exchange(cam, encode_datagram(PayloadType.INQUIRY, 5, FOCUS_POS_INQ), 1.2)
    assert [(r.kind, r.seq, r.payload[:2]) for r in replies] == [
        (PayloadType.REPLY, 5, b"\x90\x50")
    ]
    replies = _exchange(cam, encode_datagram(PayloadType.COMMAND, 6, FOCUS_DIRECT), 1.4)
    replies += _exchange(cam, encode_datagram(PayloadType.COMMAND, 6, FOCUS_DIRECT), 1.6)
    cam.poll(5.0)
    replies += [decode_datagram(d) for d, _ in cam.datagrams_to_send()]
    assert [(r.seq, r.payload.hex()) for r in replies] == [
        (6, "9041ff"),
        (6, "0f01"),  # the resend is not run twice
        (6, "9051ff"),
    ]


def test_camera_message_type_errors_and_lax_controllers() -> None:
    cam = _camera()
    [r] = _exchange(cam, encode_datagram(PayloadType.INQUIRY, 1, FOCUS_DIRECT), 1.0)
    assert (r.kind, r.payload) == (PayloadType.CONTROL_REPLY, b"\x0f\x02")
    [r] = _exchange(cam, encode_datagram(0x0300, 2, FOCUS_POS_INQ), 1.2)
    assert r.payload == b"\x0f\x02"
    # Inquiries in a command envelope, all with sequence number 0: answered every time.
    for t in (1.4, 1.6):
        [r] = _exchange(cam, encode_datagram(PayloadType.COMMAND, 0, FOCUS_POS_INQ), t)
        assert (r.kind, r.seq, r.payload[:2]) == (PayloadType.REPLY, 0, b"\x90\x50")
    assert cam.message_type_errors == 2


@pytest.mark.parametrize("late_first", [True, False])
def test_a_resent_inquiry_answered_under_the_old_number_frees_the_line(late_first: bool) -> None:
    # The answer to seq 1 was only late; seq 2 (the resend sharing its reply state) is pending.
    # Whichever answer comes first reaches the session once, and the next queued packet goes out
    # — before, a duplicate answer to the pending resend left it pending: resent, refused
    # "already performed", resent again for ever, and everything queued behind it stalled.
    ch = _connected()
    ch.send(FOCUS_POS_INQ, 0.0)
    ch.datagrams_to_send()
    ch.poll(RETRANSMIT_S)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.07)
    [again] = ch.datagrams_to_send()
    assert decode_datagram(again).seq == 2
    ch.send(FOCUS_DIRECT, 0.075)  # the session's next request waits behind seq 2
    assert ch.datagrams_to_send() == []
    answers = [(1, 0.08), (2, 0.09)] if late_first else [(2, 0.08), (1, 0.09)]
    for seq, t in answers[:1]:
        ch.receive(_reply(seq, "905003000000ff"), t)
    [command] = ch.datagrams_to_send()
    assert decode_datagram(command) == Datagram(PayloadType.COMMAND, 3, FOCUS_DIRECT)
    for seq, t in answers[1:]:
        ch.receive(_reply(seq, "905003000000ff"), t)
    assert ch.data_received() == bytes.fromhex("905003000000ff")
    ch.poll(0.1 + RETRANSMIT_S)  # no resend of the inquiry: only the command is in flight
    assert all(decode_datagram(d).seq == 3 for d in ch.datagrams_to_send())


def test_a_refused_number_answered_late_after_the_reset_reaches_the_session_once() -> None:
    # A duplicate of seq 1 reached the camera first ("already performed"), nothing else came in
    # time: RESET and resend as seq 2 — then the real answer to seq 1 arrives, and seq 2's.
    ch = _connected()
    ch.send(FOCUS_POS_INQ, 0.0)
    ch.datagrams_to_send()
    ch.receive(_reply(1, "0f01", PayloadType.CONTROL_REPLY), 0.005)
    ch.poll(RETRANSMIT_S)
    [reset] = ch.datagrams_to_send()
    assert decode_datagram(reset).kind == PayloadType.CONTROL
    ch.receive(_reply(0, "01", PayloadType.CONTROL_REPLY), RETRANSMIT_S + 0.001)
    [again] = ch.datagrams_to_send()
    assert decode_datagram(again) == Datagram(PayloadType.INQUIRY, 2, FOCUS_POS_INQ)
    ch.send(FOCUS_DIRECT, RETRANSMIT_S + 0.002)
    ch.receive(_reply(1, "905003000000ff"), RETRANSMIT_S + 0.01)  # late, under the old number
    [command] = ch.datagrams_to_send()  # the line moves on
    assert decode_datagram(command).payload == FOCUS_DIRECT
    ch.receive(_reply(2, "905003000000ff"), RETRANSMIT_S + 0.02)
    assert ch.data_received() == bytes.fromhex("905003000000ff")  # one answer, not two
