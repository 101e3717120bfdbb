"""The simulated VISCA camera, in process and in virtual time (no pty, no sleeping)."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.sim.device import INPUT_QUEUE_PACKETS, RX_WIRE_MAX_BYTES
from drivers.sim.device_motors import pan_speed_deg_s, tilt_speed_deg_s
from drivers.sim.device_types import (
    DEFAULT_FOCUS_SPEED_COUNTS_S,
    DEFAULT_ZOOM_SPEED_COUNTS_S,
    FIELD_PERIOD_S,
    DeviceConfig,
    Emission,
)
from drivers.sim.faults import Faults, FaultSpec, FaultSpecError
from drivers.sim.models import EVI_D100
from drivers.sim.server import InProcessCamera, packets
from drivers.sim.virtual_clock import VirtualClock
from drivers.visca import codec, codec_replies, codec_requests
from drivers.visca.codec_framing import Packet
from drivers.visca.codec_replies import Completion, InquiryReply, NetworkChange
from drivers.visca.codec_requests import FocusDirection, PanDirection, TiltDirection

V = FIELD_PERIOD_S


def hexes(emissions: list[Emission]) -> list[str]:
    return [raw.hex(" ").upper() for raw in packets(emissions)]


def replies(emissions: list[Emission]) -> list[tuple[float, codec_replies.Reply]]:
    return [(e.t, codec.decode_reply(Packet.from_bytes(e.data))) for e in emissions]


def manual_camera(config: DeviceConfig | None = None, **kwargs: object) -> InProcessCamera:
    """A camera after power-up with manual focus, its power-up output consumed."""
    cam = InProcessCamera(config, **kwargs)  # type: ignore[arg-type]
    cam.run_for(0.02)
    assert hexes(cam.exchange(codec_requests.FocusMode(auto=False))) == ["90 41 FF", "90 51 FF"]
    return cam


def run_to_completion(cam: InProcessCamera, socket: int, limit_s: float = 5.0) -> float:
    """Advance until Completion for ``socket``; return its time."""
    target = Completion(socket)
    sent = cam.run_until(
        cam.now() + limit_s, stop=lambda got: any(r == target for _, r in replies(got))
    )
    times = [t for t, r in replies(sent) if r == target]
    assert times, f"no Completion for socket {socket} within {limit_s} s: {hexes(sent)}"
    return times[0]


# ---- power-up and inquiries -----------------------------------------------------------------


def test_power_up_sends_network_change_and_comes_up_in_autofocus() -> None:
    cam = InProcessCamera()
    sent = cam.run_for(0.01)
    assert hexes(sent) == ["90 38 FF"]
    assert sent[0].t == 0.0
    assert hexes(cam.exchange(codec_requests.FocusModeInquiry())) == ["90 50 02 FF"]
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["90 50 02 FF"]


@pytest.mark.parametrize(
    ("request_", "expected"),
    [
        (codec_requests.VersionInquiry(), "90 50 00 01 04 0D 02 00 02 FF"),
        (codec_requests.PanTiltMaxSpeedInquiry(), "90 50 18 14 FF"),
        (codec_requests.PanTiltPositionInquiry(), "90 50 00 00 00 00 00 00 00 00 FF"),
        (codec_requests.FocusPositionInquiry(), "90 50 01 00 00 00 FF"),
        (codec_requests.ZoomPositionInquiry(), "90 50 00 00 00 00 FF"),
        (codec_requests.IFClear(), "90 50 FF"),
    ],
)
def test_inquiries_answered_without_ack_within_one_field(
    request_: codec_requests.Request, expected: str
) -> None:
    cam = InProcessCamera()
    cam.run_for(0.02)
    t_sent = cam.now()
    sent = cam.exchange(request_, within_s=0.1)
    assert hexes(sent) == [expected]
    assert 0.0 <= sent[0].t - t_sent <= V + 1e-9


def test_broadcast_if_clear_is_echoed() -> None:
    cam = InProcessCamera()
    cam.run_for(0.02)
    assert hexes(cam.exchange(b"\x88\x01\x00\x01\xff")) == ["88 01 00 01 FF"]


# ---- motion timing --------------------------------------------------------------------------


def test_focus_direct_completes_after_distance_over_speed() -> None:
    cam = manual_camera()
    start = cam.now()
    target = 0x6000
    sent = cam.exchange(codec_requests.FocusDirect(target), within_s=0.02)
    assert hexes(sent) == ["90 41 FF"]
    t_ack = sent[0].t
    assert cam.state.snapshot().focus_moving
    t_done = run_to_completion(cam, 1)
    expected = (target - 0x1000) / DEFAULT_FOCUS_SPEED_COUNTS_S
    # Completion is reported at the first field boundary after the motor stops.
    assert expected <= t_done - t_ack <= expected + V + 1e-9
    assert t_ack - start <= V + 1e-9
    assert not cam.state.snapshot().focus_moving
    assert hexes(cam.exchange(codec_requests.FocusPositionInquiry())) == ["90 50 06 00 00 00 FF"]


def test_focus_full_range_takes_about_one_and_a_half_seconds() -> None:
    cam = manual_camera()
    t0 = cam.exchange(codec_requests.FocusDirect(0x8400), within_s=0.02)[0].t
    assert run_to_completion(cam, 1) - t0 == pytest.approx(1.5, abs=V)


def test_zoom_direct_completes_after_distance_over_speed() -> None:
    cam = manual_camera()
    t_ack = cam.exchange(codec_requests.ZoomDirect(0x2000), within_s=0.02)[0].t
    t_done = run_to_completion(cam, 1)
    assert t_done - t_ack == pytest.approx(0x2000 / DEFAULT_ZOOM_SPEED_COUNTS_S, abs=V)
    assert hexes(cam.exchange(codec_requests.ZoomPositionInquiry())) == ["90 50 02 00 00 00 FF"]


@pytest.mark.parametrize(
    ("pan", "tilt", "pan_speed", "tilt_speed"),
    [
        (0x05A0, 0x0168, 0x18, 0x14),  # both positive ends at full speed
        (-0x05A0, -0x0168, 0x0A, 0x05),  # negative ends (sign handling) at slow speeds
        (-1, 1, 0x01, 0x01),  # one count either side of home
    ],
)
def test_pan_tilt_absolute_arrives_after_distance_over_speed(
    pan: int, tilt: int, pan_speed: int, tilt_speed: int
) -> None:
    cam = manual_camera()
    t_ack = cam.exchange(codec_requests.PanTiltAbsolute(pan_speed, tilt_speed, pan, tilt), 0.02)[
        0
    ].t
    t_done = run_to_completion(cam, 1, limit_s=200.0)
    pan_s = abs(pan) / EVI_D100.pan_counts_per_deg / pan_speed_deg_s(EVI_D100, pan_speed)
    tilt_s = abs(tilt) / EVI_D100.tilt_counts_per_deg / tilt_speed_deg_s(EVI_D100, tilt_speed)
    assert max(pan_s, tilt_s) <= t_done - t_ack <= max(pan_s, tilt_s) + V + 1e-9
    reply = cam.exchange(codec_requests.PanTiltPositionInquiry())
    data = codec.decode_reply(Packet.from_bytes(reply[0].data))
    assert isinstance(data, InquiryReply)
    assert codec_replies.PanTiltPosition.from_data(data.data) == codec_replies.PanTiltPosition(
        pan, tilt
    )
    snap = cam.state.snapshot()
    assert snap.pan_deg == pytest.approx(pan / EVI_D100.pan_counts_per_deg)
    assert snap.tilt_deg == pytest.approx(tilt / EVI_D100.tilt_counts_per_deg)


def test_pan_tilt_relative_adds_to_the_position_and_clamps_at_the_end_stop() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.PanTiltRelative(0x18, 0x14, 720, -144))
    run_to_completion(cam, 1)
    assert cam.state.snapshot().pan_deg == pytest.approx(50.0)
    assert cam.state.snapshot().tilt_deg == pytest.approx(-10.0)
    cam.exchange(codec_requests.PanTiltRelative(0x18, 0x14, 1440, 0))
    run_to_completion(cam, 1)
    assert cam.state.snapshot().pan_deg == pytest.approx(100.0)


def test_pan_tilt_drive_completes_at_once_and_moves_until_stopped() -> None:
    cam = manual_camera()
    drive = codec_requests.PanTiltDrive(0x0A, 0x05, PanDirection.RIGHT, TiltDirection.DOWN)
    sent = cam.exchange(drive, within_s=0.02)
    assert hexes(sent) == ["90 41 FF", "90 51 FF"]
    assert sent[0].t == sent[1].t
    t_start = sent[0].t
    cam.run_for(0.5)
    snap = cam.state.snapshot()
    assert snap.pan_tilt_moving
    elapsed = cam.now() - t_start
    assert snap.pan_deg == pytest.approx(pan_speed_deg_s(EVI_D100, 0x0A) * elapsed)
    assert snap.tilt_deg == pytest.approx(-tilt_speed_deg_s(EVI_D100, 0x05) * elapsed)
    stop = cam.exchange(codec_requests.PanTiltDrive.stop(), within_s=0.02)
    assert hexes(stop) == ["90 41 FF", "90 51 FF"]
    held = cam.state.snapshot().pan_deg
    cam.run_for(0.5)
    assert not cam.state.snapshot().pan_tilt_moving
    assert cam.state.snapshot().pan_deg == held


def test_home_and_reset_return_to_centre() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.PanTiltAbsolute(0x18, 0x14, 720, 144))
    run_to_completion(cam, 1)
    t0 = cam.exchange(codec_requests.PanTiltHome(), 0.02)[0].t
    assert run_to_completion(cam, 1) - t0 == pytest.approx(50 / 300, abs=V)
    assert cam.state.snapshot().pan_deg == pytest.approx(0.0, abs=1e-9)
    t0 = cam.exchange(codec_requests.PanTiltReset(), 0.02)[0].t
    t_done = run_to_completion(cam, 1)
    # To the lower end stops and back at full speed: pan (100° at 300°/s) is the slow axis.
    assert t_done - t0 == pytest.approx(2 * 100 / 300, abs=2 * V)
    assert cam.state.pan.moved_between(t0, t_done)
    snap = cam.state.snapshot()
    assert (snap.pan_deg, snap.tilt_deg) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_focus_drive_far_near_stop() -> None:
    cam = manual_camera(DeviceConfig(focus_speed_counts_s=8000.0))
    cam.exchange(codec_requests.FocusDirect(0x4000))
    run_to_completion(cam, 1)
    sent = cam.exchange(codec_requests.FocusDrive(FocusDirection.NEAR, speed=7), within_s=0.02)
    assert hexes(sent) == ["90 41 FF", "90 51 FF"]
    cam.run_for(0.25)
    elapsed = cam.now() - sent[0].t
    assert cam.state.snapshot().focus_counts == pytest.approx(0x4000 + 8000 * elapsed)
    assert cam.state.snapshot().focus_moving
    t_stop = cam.exchange(codec_requests.FocusDrive(FocusDirection.STOP))[0].t
    here = cam.state.focus.position(t_stop)
    assert not cam.state.snapshot().focus_moving
    assert cam.state.snapshot().focus_counts == here
    t0 = cam.exchange(codec_requests.FocusDrive(FocusDirection.FAR, speed=0), within_s=0.02)[0].t
    cam.run_for(0.5)
    rate = (here - cam.state.snapshot().focus_counts) / (cam.now() - t0)
    assert rate == pytest.approx(1000.0)  # speed 0 is 1/8 of the full 8000 counts/s


def test_one_push_af_moves_focus_to_the_oracle() -> None:
    cam = manual_camera()
    cam.device.focus_oracle = lambda t: 0x3000
    cam.exchange(codec_requests.FocusOnePush())
    run_to_completion(cam, 1)
    assert cam.state.snapshot().focus_counts == 0x3000


# ---- sockets, cancel, errors ----------------------------------------------------------------


def test_two_sockets_buffer_full_and_inquiries_while_busy() -> None:
    cam = manual_camera()
    assert hexes(cam.exchange(codec_requests.FocusDirect(0x8000))) == ["90 41 FF"]
    assert hexes(cam.exchange(codec_requests.PanTiltAbsolute(0x01, 0x01, 100, 0))) == ["90 42 FF"]
    assert hexes(cam.exchange(codec_requests.ZoomDirect(0x100))) == ["90 60 03 FF"]
    assert hexes(cam.exchange(codec_requests.FocusPositionInquiry()))[0].startswith("90 50")
    assert cam.device.busy_sockets() == [1, 2]
    assert run_to_completion(cam, 1) < run_to_completion(cam, 2, limit_s=10.0)
    assert hexes(cam.exchange(codec_requests.ZoomDirect(0x100), 0.02)) == ["90 41 FF"]


def test_cancel_running_command_stops_motor_without_completion() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.FocusDirect(0x8000), within_s=0.2)
    assert hexes(cam.exchange(codec_requests.Cancel(1))) == ["90 61 04 FF"]
    stopped = cam.state.snapshot().focus_counts
    later = cam.run_for(3.0)
    assert hexes(later) == []
    assert cam.state.snapshot().focus_counts == stopped
    assert 0x1000 < stopped < 0x8000
    assert hexes(cam.exchange(codec_requests.Cancel(2))) == ["90 62 05 FF"]


def test_manual_focus_in_autofocus_is_not_executable() -> None:
    cam = InProcessCamera()
    cam.run_for(0.02)
    assert hexes(cam.exchange(codec_requests.FocusDirect(0x2000))) == ["90 61 41 FF"]
    assert hexes(cam.exchange(codec_requests.FocusDrive(FocusDirection.FAR))) == ["90 61 41 FF"]
    assert hexes(cam.exchange(codec_requests.FocusOnePush())) == ["90 61 41 FF"]
    assert cam.device.busy_sockets() == []
    assert hexes(cam.exchange(codec_requests.ZoomDirect(0x4000))) == [
        "90 41 FF"
    ]  # zoom is fine in AF
    # While socket 1 runs, the refused command names socket 2.
    assert hexes(cam.exchange(codec_requests.FocusDirect(0x2000))) == ["90 62 41 FF"]


@pytest.mark.parametrize(
    "raw",
    [
        "81 01 04 48 00 0F 0F 0F FF",  # focus below the far end 0x1000
        "81 01 04 48 08 04 00 01 FF",  # focus beyond the near end 0x8400
        "81 01 04 47 04 00 00 01 FF",  # zoom beyond 0x4000
        "81 01 06 02 18 14 00 05 0A 01 00 00 00 00 FF",  # pan 0x05A1 > +100°
        "81 01 06 02 18 14 0F 0A 05 0F 00 00 00 00 FF",  # pan 0xFA5F < −100°
        "81 01 06 02 18 14 00 00 00 00 00 01 06 09 FF",  # tilt 0x0169 > +25°
        "81 01 06 01 00 01 03 03 FF",  # pan speed 00
        "81 01 06 01 19 01 01 03 FF",  # pan speed 0x19
        "81 01 06 01 01 15 03 01 FF",  # tilt speed 0x15 (EVI-D100 max 0x14)
        "81 01 06 01 01 01 04 03 FF",  # pan direction 04
        "81 01 04 48 01 00 00 FF",  # focus direct with 3 nibbles
        "81 01 04 48 01 00 00 00 00 FF",  # … and with 5
        "81 01 04 38 05 FF",  # focus mode 05
        "81 01 04 00 04 FF",  # power 04
        "81 01 7E 7E FF",  # unknown command
        "81 09 04 7E FF",  # unknown inquiry
        "81 01 04 48 01 00 10 00 FF",  # a data byte that is not a nibble
    ],
)
def test_malformed_or_out_of_range_is_a_syntax_error(raw: str) -> None:
    cam = manual_camera()
    assert hexes(cam.exchange(bytes.fromhex(raw))) == ["90 60 02 FF"]
    assert cam.device.busy_sockets() == []


@pytest.mark.parametrize("socket", [0, 3, 0x0F])
def test_cancel_of_a_socket_the_camera_does_not_have_is_no_socket(socket: int) -> None:
    cam = manual_camera()
    assert hexes(cam.exchange(bytes([0x81, 0x20 | socket, 0xFF]))) == [f"90 6{socket:X} 05 FF"]


def test_overlong_packet_is_a_message_length_error_and_the_camera_resynchronises() -> None:
    cam = manual_camera()
    overlong = b"\x81\x01\x04" + bytes(15) + b"\xff"  # 19 bytes > 16
    assert hexes(cam.exchange(overlong)) == ["90 60 01 FF"]
    assert hexes(
        cam.exchange(b"\x12\x34" + codec.encode_request(codec_requests.PowerInquiry(), 1))
    ) == ["90 50 02 FF"]


def test_packets_for_other_cameras_and_from_cameras_are_ignored() -> None:
    cam = manual_camera()
    assert hexes(cam.exchange(codec.encode_request(codec_requests.PowerInquiry(), 2))) == []
    assert hexes(cam.exchange(b"\x90\x50\x02\xff")) == []  # a reply looped back
    assert cam.device.stats.ignored == 2


def test_newer_pan_tilt_command_completes_the_running_move() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.PanTiltAbsolute(0x01, 0x01, 1000, 0), within_s=0.2)
    sent = cam.exchange(codec_requests.PanTiltDrive.stop())
    assert hexes(sent) == ["90 42 FF", "90 51 FF", "90 52 FF"]
    assert not cam.state.snapshot().pan_tilt_moving
    assert hexes(cam.run_for(2.0)) == []


def test_if_clear_ends_running_commands_without_reply() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.FocusDirect(0x8000), within_s=0.1)
    assert hexes(cam.exchange(codec_requests.IFClear())) == ["90 50 FF"]
    assert cam.device.busy_sockets() == []
    assert not cam.state.snapshot().focus_moving
    assert hexes(cam.run_for(2.0)) == []


def test_standby_refuses_motion_and_power_on_completes_after_boot() -> None:
    cam = manual_camera(DeviceConfig(power_on_s=0.5))
    assert hexes(cam.exchange(codec_requests.CamPower(on=False))) == ["90 41 FF", "90 51 FF"]
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["90 50 03 FF"]
    assert hexes(cam.exchange(codec_requests.ZoomDirect(0x100))) == ["90 61 41 FF"]
    t0 = cam.exchange(codec_requests.CamPower(on=True), within_s=0.02)[0].t
    assert run_to_completion(cam, 1) - t0 == pytest.approx(0.5, abs=V)
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["90 50 02 FF"]
    assert hexes(cam.exchange(codec_requests.CamPower(on=True))) == ["90 41 FF", "90 51 FF"]


# ---- fields, pacing, addressing -------------------------------------------------------------


def test_at_most_one_message_per_video_field() -> None:
    cam = manual_camera()
    t_sent = cam.now()
    for _ in range(4):
        cam.send(codec_requests.PowerInquiry())
    sent = cam.run_for(0.2)
    times = [e.t for e in sent]
    assert len(times) == 4
    assert times[0] - t_sent <= V + 1e-9
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert gaps == pytest.approx([V] * 3)


def test_input_queue_is_bounded() -> None:
    cam = manual_camera()
    cam.send(codec.encode_request(codec_requests.PowerInquiry(), 1) * (INPUT_QUEUE_PACKETS + 5))
    assert len(packets(cam.run_for(1.0))) == INPUT_QUEUE_PACKETS
    assert cam.device.stats.input_overflow == 5


def test_pacing_models_wire_time_both_ways() -> None:
    byte_s = 10 / 9600
    cam = manual_camera(DeviceConfig(pace=True, baud=9600))
    cam.run_until(math.ceil(cam.now() / V) * V + 0.001)  # just after a field boundary
    t_sent = cam.now()
    sent = cam.exchange(codec_requests.VersionInquiry(), within_s=0.1)
    arrived = t_sent + 5 * byte_s
    field = math.ceil(arrived / V) * V
    assert sent[0].t == pytest.approx(field + 10 * byte_s)


def test_address_set_takes_the_given_address_and_replies_with_the_next() -> None:
    cam = InProcessCamera()
    cam.run_for(0.02)
    assert hexes(cam.exchange(codec_requests.AddressSet())) == ["88 30 02 FF"]
    assert cam.device.address == 1
    # As the third camera of a chain it takes 3 and answers from B0.
    cam3 = InProcessCamera(DeviceConfig(address=3))
    assert hexes(cam3.run_for(0.02)) == ["B0 38 FF"]
    assert hexes(cam3.exchange(codec_requests.AddressSet())) == ["88 30 04 FF"]
    assert hexes(cam3.exchange(codec.encode_request(codec_requests.PowerInquiry(), 3))) == [
        "B0 50 02 FF"
    ]
    assert hexes(cam3.exchange(codec.encode_request(codec_requests.PowerInquiry(), 1))) == []
    # A camera further down a chain sees 30 0w with w > 1.
    assert hexes(cam.exchange(b"\x88\x30\x04\xff")) == ["88 30 05 FF"]
    assert cam.device.address == 4


def test_reply_from_a0_quirk() -> None:
    cam = InProcessCamera(DeviceConfig(reply_from_a0=True))
    assert hexes(cam.run_for(0.02)) == ["A0 38 FF"]
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["A0 50 02 FF"]
    assert hexes(cam.exchange(codec_requests.AddressSet())) == ["88 30 02 FF"]


# ---- faults ---------------------------------------------------------------------------------


def test_fault_spec_grammar_round_trips_and_names_bad_keys() -> None:
    text = (
        "seed=3,drop=0.01,corrupt=0.01,duplicate=0.01,delay=0.02:0.05,lose_completion=0.05,"
        "garbage=0.01,network_change_every=5"
    )
    spec = FaultSpec.parse(text)
    assert spec.seed == 3
    assert spec.delay == 0.02
    assert spec.delay_s == 0.05
    assert spec.network_change_every == 5.0
    assert FaultSpec.parse(str(spec)) == spec
    assert FaultSpec.parse(" ") == FaultSpec()
    assert not FaultSpec.parse("seed=9").active
    assert FaultSpec.parse("direction = rx , power_cycle_every=2").direction == "rx"
    with pytest.raises(FaultSpecError, match="'dorp'"):
        FaultSpec.parse("dorp=0.1")
    with pytest.raises(FaultSpecError, match=r"'drop'.*probability"):
        FaultSpec.parse("drop=2")
    with pytest.raises(FaultSpecError, match="'delay'"):
        FaultSpec.parse("delay=0.1:x")
    with pytest.raises(FaultSpecError, match="KEY=VALUE"):
        FaultSpec.parse("drop")
    with pytest.raises(FaultSpecError, match="'seed'"):
        FaultSpec.parse("seed=abc")


MANUAL = DeviceConfig(autofocus_at_power_up=False)


def _noisy_session(spec: str) -> list[Emission]:
    cam = InProcessCamera(MANUAL, faults=Faults(spec))
    out: list[Emission] = []
    for counts in range(0x1000, 0x8000, 0x0800):
        out += cam.exchange(codec_requests.FocusDirect(counts), within_s=0.6)
        out += cam.exchange(codec_requests.PanTiltPositionInquiry(), within_s=0.05)
    return out


def test_faults_are_deterministic_for_a_seed() -> None:
    spec = "seed=7,drop=0.02,corrupt=0.02,duplicate=0.02,delay=0.1:0.03,garbage=0.1"
    first, second = _noisy_session(spec), _noisy_session(spec)
    assert first == second
    clean = _noisy_session("seed=7")
    assert first != clean
    assert _noisy_session(spec.replace("seed=7", "seed=8")) != first


def test_lose_completion_and_garbage() -> None:
    cam = InProcessCamera(MANUAL, faults=Faults("seed=1,lose_completion=1"))
    cam.run_for(0.02)
    assert hexes(cam.exchange(codec_requests.FocusDirect(0x2000))) == ["90 41 FF"]
    assert hexes(cam.run_for(2.0)) == []
    assert cam.device.busy_sockets() == []  # the camera finished; only the reply is gone
    assert cam.device.stats.lost_completions == 1
    noisy = InProcessCamera(MANUAL, faults=Faults("seed=1,garbage=1,direction=tx"))
    noisy.run_for(0.02)
    raw = b"".join(e.data for e in noisy.exchange(codec_requests.PowerInquiry()))
    assert raw.endswith(b"\x90\x50\x02\xff")
    assert len(raw) > 4


def test_delay_stalls_the_stream_in_order() -> None:
    cam = InProcessCamera(MANUAL, faults=Faults("seed=1,delay=1:0.25"))
    cam.run_for(0.5)
    t_sent = cam.now()
    cam.send(codec_requests.PowerInquiry())
    cam.send(codec_requests.FocusModeInquiry())
    sent = cam.run_for(1.0)
    assert hexes(sent) == ["90 50 02 FF", "90 50 03 FF"]
    assert sent[0].t - t_sent >= 0.25
    assert sent[1].t - sent[0].t >= 0.25


def test_rx_drop_makes_the_camera_miss_commands() -> None:
    cam = InProcessCamera(MANUAL, faults=Faults("seed=1,drop=1,direction=rx"))
    assert hexes(cam.run_for(0.02)) == ["90 38 FF"]  # output is clean
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == []


def test_periodic_network_change() -> None:
    cam = InProcessCamera(faults="network_change_every=0.5")
    sent = cam.run_for(1.6)
    assert [round(e.t, 6) for e in sent] == [0.0, 0.5, 1.0, 1.5]
    assert all(r == NetworkChange() for _, r in replies(sent))


def test_power_cycle_loses_state_and_announces_itself() -> None:
    cam = manual_camera()
    cam.exchange(codec_requests.FocusDirect(0x8000), within_s=0.1)
    cam.faults.power_cycle(off_s=0.3)
    t_off = cam.now()
    assert hexes(cam.exchange(codec_requests.PowerInquiry(), within_s=0.25)) == []  # dead
    sent = cam.run_for(0.1)
    assert hexes(sent) == ["90 38 FF"]
    assert sent[0].t == pytest.approx(t_off + 0.3)
    assert cam.device.busy_sockets() == []
    assert hexes(cam.exchange(codec_requests.FocusModeInquiry())) == ["90 50 02 FF"]  # back in AF


def test_periodic_power_cycle() -> None:
    cam = InProcessCamera(faults="power_cycle_every=1,power_off=0.2")
    sent = cam.run_for(2.5)
    assert [round(e.t, 6) for e in sent] == [0.0, 1.2, 2.4]


def test_silent_camera_reads_but_never_answers() -> None:
    cam = manual_camera()
    cam.faults.set_silent(True)
    assert hexes(cam.exchange(codec_requests.FocusDirect(0x3000), within_s=2.0)) == []
    assert cam.state.snapshot().focus_counts == 0x1000
    cam.faults.set_silent(False)
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["90 50 02 FF"]


def test_in_process_close_and_reopen_port() -> None:
    cam = manual_camera()
    cam.faults.close_port()
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == []
    cam.faults.reopen_port()
    assert hexes(cam.run_for(0.02)) == ["90 38 FF"]
    assert hexes(cam.exchange(codec_requests.PowerInquiry())) == ["90 50 02 FF"]


def test_unbound_faults_say_what_to_do() -> None:
    with pytest.raises(RuntimeError, match="SimCameraServer"):
        Faults().power_cycle()


def test_virtual_clock_never_goes_back() -> None:
    clock = VirtualClock(1.0)
    assert clock.advance(0.5) == 1.5
    with pytest.raises(ValueError, match="cannot go back"):
        clock.set(1.0)


# ---- robustness -----------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(noise=st.binary(max_size=64), chunk=st.integers(min_value=1, max_value=8))
def test_no_byte_stream_breaks_the_camera(noise: bytes, chunk: int) -> None:
    cam = InProcessCamera(MANUAL)
    for i in range(0, len(noise), chunk):
        cam.send(noise[i : i + chunk])
        cam.run_for(0.005)
    cam.run_for(0.5)
    # Whatever came before, a terminator resynchronises and the camera answers again.
    address = cam.device.address  # the noise may have held an Address Set
    inquiry = codec.encode_request(codec_requests.VersionInquiry(), address)
    sent = cam.exchange(b"\xff" + inquiry, within_s=0.5)
    assert packets(sent)[-1] == codec.encode_reply(
        InquiryReply(codec_replies.Version(0x0001, 0x040D, 0x0200, 2).to_data()), address
    )


def test_commands_fed_one_byte_at_a_time() -> None:
    cam = InProcessCamera(MANUAL)
    cam.run_for(0.02)
    for byte in codec.encode_request(codec_requests.FocusDirect(0x2000), 1):
        cam.send(bytes((byte,)))
        cam.run_for(0.001)
    assert hexes(cam.run_for(1.0)) == ["90 41 FF", "90 51 FF"]


def test_bytes_faster_than_the_baud_rate_overflow_the_receive_buffer() -> None:
    cam = InProcessCamera(DeviceConfig(pace=True))
    inquiry = codec.encode_request(codec_requests.PowerInquiry(), 1)
    for _ in range(2000):  # 10 000 bytes at once: over 10 s of wire time at 9600 baud
        cam.send(inquiry)
    assert cam.device.stats.input_overflow > 0
    assert cam.device.stats.bytes_in <= RX_WIRE_MAX_BYTES
