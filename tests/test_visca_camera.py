"""Typed camera API against the simulated camera over a real pty, and unit conversion."""

from __future__ import annotations

import asyncio
import dataclasses
import time

import pytest

from drivers.sim.device_types import DeviceConfig
from drivers.visca import codec_replies
from drivers.visca.camera import EVI_D70, EVI_D100, Camera, SpeedCode, profile_for
from drivers.visca.errors import (
    ViscaCancelledError,
    ViscaError,
    ViscaNotExecutableError,
    ViscaTimeoutError,
)
from drivers.visca.link import ViscaLink
from tests.visca_support import FAST, WAIT_S, SimChain, sim_camera

# A move's wall time may exceed distance/speed by the field it starts on, the field its end is
# noticed on and the reply's trip through the pty; a loaded machine adds scheduling delay.
MOVE_SLACK_S = 0.3


async def _until_pan(camera: Camera, predicate: object) -> float:
    """Poll the pan position (one inquiry round trip each) until ``predicate(pan)``."""
    async with asyncio.timeout(WAIT_S):
        while True:
            pan, _ = await camera.pan_tilt_position()
            if predicate(pan):  # type: ignore[operator]
                return pan


async def test_initialize_sets_manual_focus_and_powers_on() -> None:
    async with sim_camera() as (server, link, camera):
        assert camera.version_info == codec_replies.Version(0x0001, 0x040D, 0x0200, 2)
        assert server.state.autofocus is False
        assert link.chain_length == 1
        await camera.power(False)
        assert await camera.power_is_on() is False
        await camera.initialize()
        assert server.state.powered is True
        assert await camera.focus_is_auto() is False


async def test_focus_direct_then_position_inquiry_agree() -> None:
    fast_lens = DeviceConfig(focus_speed_counts_s=0x7400 / 0.3)
    async with sim_camera(fast_lens) as (server, _, camera):
        for target in (0x7000, 0x1234, 0x8400, 0x1000):
            await camera.focus_direct(target)
            assert not server.state.focus.moving(server.state.now())  # the lens has stopped
            assert await camera.focus_position() == target
            assert server.state.snapshot().focus_counts == target


async def test_zoom_direct_then_position_inquiry_agree() -> None:
    async with sim_camera() as (_, _, camera):
        await camera.zoom_direct(0x2345)
        assert await camera.zoom_position() == 0x2345


async def test_absolute_move_arrives_in_about_distance_over_speed() -> None:
    async with sim_camera() as (server, _, camera):
        speed = 34.0  # code 0E exactly
        start = time.monotonic()
        await camera.pan_tilt_absolute(30.0, -5.0, speed)
        elapsed = time.monotonic() - start
        expected = 30.0 / speed
        assert 0.9 * expected <= elapsed <= expected + MOVE_SLACK_S
        pan, tilt = await camera.pan_tilt_position()
        assert pan == pytest.approx(30.0, abs=1 / 14.4)
        assert tilt == pytest.approx(-5.0, abs=1 / 14.4)
        assert server.state.snapshot().pan_deg == pytest.approx(30.0, abs=0.01)
        await camera.home()
        assert await camera.pan_tilt_position() == (0.0, 0.0)


async def test_relative_move_and_speed_codes() -> None:
    async with sim_camera() as (_, _, camera):
        await camera.pan_tilt_absolute(10.0, 0.0, SpeedCode(0x18))
        await camera.pan_tilt_relative(-15.0, 2.5, SpeedCode(0x18))
        pan, tilt = await camera.pan_tilt_position()
        assert pan == pytest.approx(-5.0, abs=1 / 14.4)
        assert tilt == pytest.approx(2.5, abs=1 / 14.4)


async def test_drive_and_stop() -> None:
    async with sim_camera() as (server, _, camera):
        await camera.pan_tilt_drive(-20.0, 10.0)
        assert server.state.pan.moving(server.state.now())
        await _until_pan(camera, lambda pan: pan < -1.0)
        _, tilt_now = await camera.pan_tilt_position()
        assert tilt_now > 0  # up is positive
        await camera.pan_tilt_stop()
        now = server.state.now()
        assert not server.state.pan.moving(now)
        assert not server.state.tilt.moving(now)
        assert await camera.pan_tilt_position() == await camera.pan_tilt_position()


async def test_focus_and_pan_tilt_in_flight_together_on_two_sockets() -> None:
    async with sim_camera() as (server, _, camera):
        focus = await camera.start_focus_direct(0x8000)
        move = await camera.start_pan_tilt_absolute(20.0, 10.0, 100.0)
        sockets = {await focus.acked(), await move.acked()}
        assert sockets == {1, 2}
        now = server.state.now()
        assert server.state.focus.moving(now)
        assert server.state.pan.moving(now)
        # An inquiry is answered while both sockets are busy.
        assert 0x1000 <= await camera.focus_position() <= 0x8000
        await asyncio.wait_for(asyncio.gather(focus.completed(), move.completed()), WAIT_S)
        assert await camera.focus_position() == 0x8000
        assert await camera.pan_tilt_position() == pytest.approx((20.0, 10.0), abs=0.07)
        assert codec_replies.ErrorCode.BUFFER_FULL not in server.device.stats.errors_out


async def test_cancel_stops_a_move_part_way() -> None:
    async with sim_camera() as (server, _, camera):
        move = await camera.start_pan_tilt_absolute(50.0, 0.0, 2.0)
        socket = await move.acked()
        await _until_pan(camera, lambda pan: pan > 0.1)
        assert await camera.cancel(socket) is True
        with pytest.raises(ViscaCancelledError) as info:
            await move.completed()
        assert info.value.socket == socket
        assert not server.state.pan.moving(server.state.now())
        pan, _ = await camera.pan_tilt_position()
        assert 0.0 < pan < 50.0
        assert await camera.cancel(socket) is False  # idle socket


async def test_stop_with_both_sockets_busy_cancels_the_move() -> None:
    async with sim_camera() as (server, _, camera):
        move = await camera.start_pan_tilt_absolute(-60.0, 0.0, 4.7)
        focus = await camera.start_focus_direct(0x8400)
        await move.acked()
        await focus.acked()
        await camera.pan_tilt_stop()
        assert not server.state.pan.moving(server.state.now())
        with pytest.raises(ViscaCancelledError):
            await move.completed()
        await asyncio.wait_for(focus.completed(), WAIT_S)
        assert codec_replies.ErrorCode.BUFFER_FULL not in server.device.stats.errors_out


async def test_not_executable_is_a_typed_exception() -> None:
    async with sim_camera() as (_, _, camera):
        await camera.focus_mode(True)
        with pytest.raises(ViscaNotExecutableError) as info:
            await camera.focus_direct(0x3000)
        assert info.value.code == 0x41
        assert info.value.socket in (1, 2)
        await camera.focus_mode(False)
        await camera.focus_direct(0x3000)
        assert await camera.focus_position() == 0x3000


async def test_silent_camera_times_out_cleanly_then_recovers() -> None:
    async with sim_camera(retries=0) as (server, link, camera):
        server.set_silent(True)
        with pytest.raises(ViscaTimeoutError) as inquiry:
            await camera.focus_position()
        assert inquiry.value.timeout_s == FAST.inquiry_s
        with pytest.raises(ViscaTimeoutError) as command:
            await camera.focus_direct(0x2000)
        assert command.value.wait == "ACK"
        server.set_silent(False)
        await camera.focus_direct(0x2000)
        assert await camera.focus_position() == 0x2000
        assert link.health().timeouts["ACK"] == 1


async def test_replies_from_a0_are_understood() -> None:
    async with sim_camera(DeviceConfig(reply_from_a0=True)) as (_, _, camera):
        await camera.focus_direct(0x4567)
        assert await camera.focus_position() == 0x4567


async def test_several_cameras_on_one_daisy_chain() -> None:
    async with SimChain(2) as chain, ViscaLink(chain.path, timeouts=FAST) as link:
        first, second = Camera(link, 1), Camera(link, 2)
        await first.initialize()
        await second.initialize()
        assert link.chain_length == 2
        await asyncio.gather(first.focus_direct(0x2000), second.focus_direct(0x6000))
        await asyncio.gather(
            first.pan_tilt_absolute(10.0, 0.0, 300.0), second.pan_tilt_absolute(-10.0, 0.0, 300.0)
        )
        assert await first.focus_position() == 0x2000
        assert await second.focus_position() == 0x6000
        assert chain.states[0].snapshot().pan_deg == pytest.approx(10.0, abs=0.01)
        assert chain.states[1].snapshot().pan_deg == pytest.approx(-10.0, abs=0.01)
        with pytest.raises(ViscaError, match="no camera at address 3"):
            await Camera(link, 3).initialize()


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda c: c.focus_direct(0x0FFF), "counts"),
        (lambda c: c.focus_direct(0x8401), "counts"),
        (lambda c: c.zoom_direct(0x4001), "counts"),
        (lambda c: c.pan_tilt_absolute(100.5, 0.0), "pan_deg"),
        (lambda c: c.pan_tilt_absolute(0.0, -25.1), "tilt_deg"),
        (lambda c: c.pan_tilt_absolute(0.0, float("nan")), "tilt_deg"),
        (lambda c: c.pan_tilt_absolute(0.0, 0.0, 301.0), "speed"),
        (lambda c: c.pan_tilt_absolute(0.0, 0.0, -1.0), "speed"),
        (lambda c: c.pan_tilt_absolute(0.0, 0.0, SpeedCode(0)), "speed code"),
        (lambda c: c.pan_tilt_relative(201.0, 0.0), "pan_deg"),
        (lambda c: c.pan_tilt_drive(400.0, 0.0), "pan_speed_deg_s"),
        (lambda c: c.pan_tilt_drive(0.0, -126.0), "tilt_speed_deg_s"),
        (lambda c: c.focus_drive("far", 8), "speed"),
        (lambda c: c.focus_drive("sideways"), "direction"),
    ],
)
async def test_out_of_range_arguments_raise_before_any_byte(call: object, field: str) -> None:
    async with sim_camera() as (server, link, camera):
        sent, received = link.health().bytes_out, server.device.stats.bytes_in
        with pytest.raises(ValueError, match=field):
            await call(camera)  # type: ignore[operator]
        assert link.health().bytes_out == sent
        assert server.device.stats.bytes_in == received


# ---- conversion (no I/O) ----------------------------------------------------------------------


def test_speed_mapping_picks_the_nearest_code() -> None:
    assert EVI_D100.pan_speed_code(34.0) == 0x0E
    assert EVI_D100.pan_speed_code(0.5) == 0x01  # never 00
    assert EVI_D100.pan_speed_code(None) == 0x18
    assert EVI_D100.tilt_speed_code(300.0) == 0x14  # capped at the fastest tilt
    assert EVI_D100.pan_speed_code(SpeedCode(5)) == 5
    assert EVI_D100.pan_to_counts(-100.0) == -0x5A0
    assert EVI_D100.tilt_to_counts(25.0) == 0x168


def test_evi_d70_profile_ranges() -> None:
    assert profile_for("EVI-D70") is EVI_D70
    assert EVI_D70.pan_to_counts(-170.0) == -2267  # 0xF725
    assert EVI_D70.tilt_to_counts(90.0) == 1200  # 0x04B0
    assert EVI_D70.tilt_to_counts(-30.0) == -400  # 0xFE70
    assert EVI_D70.max_pan_speed_code == 0x18
    assert EVI_D70.max_tilt_speed_code == 0x17
    with pytest.raises(ValueError, match="tilt_deg"):
        EVI_D70.tilt_to_counts(-31.0)
    with pytest.raises(ValueError, match="known models"):
        profile_for("EVI-H100")


async def test_early_completion_profile_confirms_with_a_position_inquiry() -> None:
    early = dataclasses.replace(EVI_D100, focus_completion_early=True)
    async with sim_camera(profile=early) as (_, link, camera):
        before = link.health().replies.get("InquiryReply", 0)
        await camera.focus_direct(0x2400)
        assert link.health().replies["InquiryReply"] == before + 1
