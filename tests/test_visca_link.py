"""VISCA link over real ptys: reply matching against a scripted camera, recovery against the sim."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import random

import pytest

from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import FaultSpec
from drivers.visca import codec, codec_requests
from drivers.visca.camera import EVI_D100
from drivers.visca.errors import (
    LinkDownError,
    ViscaBufferFullError,
    ViscaCancelledError,
    ViscaError,
    ViscaNotExecutableError,
    ViscaTimeoutError,
)
from drivers.visca.link import ViscaLink
from drivers.visca.session_types import LinkTimeouts
from tests.visca_support import FAST, WAIT_S, ScriptedCamera, reinit_event, sim_camera

FOCUS = codec.encode_request(codec_requests.FocusDirect(0x2000), 1)
ZOOM = codec.encode_request(codec_requests.ZoomDirect(0x1000), 1)
HOME = codec.encode_request(codec_requests.PanTiltHome(), 1)
STOP = codec.encode_request(codec_requests.PanTiltDrive.stop(), 1)
FOCUS_POS_INQ = codec.encode_request(codec_requests.FocusPositionInquiry(), 1)


async def _sync(cam: ScriptedCamera, link: ViscaLink) -> None:
    """Round trip one inquiry: every byte the camera sent before has been processed after it."""
    task = asyncio.create_task(link.inquire(1, codec_requests.FocusPositionInquiry()))
    assert await cam.expect() == FOCUS_POS_INQ
    cam.send("90 50 01 02 03 04 FF")
    assert (await asyncio.wait_for(task, WAIT_S)).counts == 0x1234


# ---- matching, against a scripted camera -----------------------------------------------------


async def test_ack_and_completion_in_one_read() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        handle = link.submit(1, codec_requests.FocusDirect(0x2000))
        assert await cam.expect() == FOCUS
        cam.send("90 41 FF 90 51 FF")
        await asyncio.wait_for(handle.completed(), WAIT_S)
        assert handle.socket == 1
        assert link.health().stray_replies == 0


async def test_late_completion_is_never_taken_for_the_next_command() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        first = link.submit(1, codec_requests.FocusDirect(0x2000), completion_timeout=0.05)
        assert await cam.expect() == FOCUS
        cam.send("90 41 FF")
        with pytest.raises(ViscaTimeoutError) as info:
            await asyncio.wait_for(first.completed(), WAIT_S)
        assert info.value.wait == "Completion"
        # The link cancels the socket it gave up on; the camera says it is already idle.
        assert await cam.expect() == bytes.fromhex("81 21 FF")
        cam.send("90 61 05 FF")
        second = link.submit(1, codec_requests.ZoomDirect(0x1000))
        assert await cam.expect() == ZOOM
        cam.send("90 51 FF")  # the first command's Completion, late
        cam.send("90 41 FF")  # ACK of the second, in the same socket
        await _sync(cam, link)
        assert second.socket == 1
        assert not second.done()
        assert link.health().stray_replies >= 1
        cam.send("90 51 FF")
        await asyncio.wait_for(second.completed(), WAIT_S)


async def test_completions_are_matched_per_socket_and_inquiries_answer_while_busy() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        focus = link.submit(1, codec_requests.FocusDirect(0x2000))
        assert await cam.expect() == FOCUS
        cam.send("90 41 FF")
        home = link.submit(1, codec_requests.PanTiltHome())
        assert await cam.expect() == HOME
        cam.send("90 42 FF")
        third = link.submit(1, codec_requests.ZoomDirect(0x1000))
        # Both sockets busy: the third waits in the queue; an inquiry still goes out.
        await _sync(cam, link)
        assert cam.received.empty()
        cam.send("90 52 FF")  # socket 2 = Home completes first
        await asyncio.wait_for(home.completed(), WAIT_S)
        assert not focus.done()
        assert await cam.expect() == ZOOM  # a socket freed: the queued command goes now
        cam.send("90 42 FF 90 51 FF 90 52 FF")
        await asyncio.wait_for(focus.completed(), WAIT_S)
        await asyncio.wait_for(third.completed(), WAIT_S)


async def test_stop_jumps_the_queue() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        link.submit(1, codec_requests.FocusDirect(0x2000))
        assert await cam.expect() == FOCUS
        cam.send("90 41 FF")
        link.submit(1, codec_requests.PanTiltHome())
        assert await cam.expect() == HOME
        cam.send("90 42 FF")
        zoom = link.submit(1, codec_requests.ZoomDirect(0x1000))
        stop = link.submit(1, codec_requests.PanTiltDrive.stop())
        cam.send("90 52 FF")  # Home ends: one socket free
        assert await cam.expect() == STOP  # the Stop overtook the queued Zoom Direct
        cam.send("90 42 FF 90 52 FF")
        await asyncio.wait_for(stop.completed(), WAIT_S)
        assert await cam.expect() == ZOOM
        cam.send("90 42 FF 90 52 FF")
        await asyncio.wait_for(zoom.completed(), WAIT_S)


async def test_error_replies_are_typed_and_carry_code_and_socket() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        task = asyncio.create_task(link.command(1, codec_requests.FocusDirect(0x2000)))
        assert await cam.expect() == FOCUS
        cam.send("90 62 41 FF")  # not executable, instead of the ACK
        with pytest.raises(ViscaNotExecutableError) as info:
            await asyncio.wait_for(task, WAIT_S)
        assert (info.value.code, info.value.socket, info.value.address) == (0x41, 2, 1)
        assert "manual focus" in str(info.value)
        inquiry = asyncio.create_task(link.inquire(1, codec_requests.VersionInquiry()))
        await cam.expect()
        cam.send("90 60 02 FF")  # syntax error answers the inquiry
        with pytest.raises(ViscaError) as syntax:
            await asyncio.wait_for(inquiry, WAIT_S)
        assert getattr(syntax.value, "code", None) == 0x02
        assert link.health().errors_by_code == {0x41: 1, 0x02: 1}


async def test_cancel_reports_cancelled_and_idle() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        handle = link.submit(1, codec_requests.FocusDirect(0x2000))
        assert await cam.expect() == FOCUS
        cam.send("90 41 FF")
        assert await asyncio.wait_for(handle.acked(), WAIT_S) == 1
        cancelled = asyncio.create_task(link.cancel(1, 1))
        assert await cam.expect() == bytes.fromhex("81 21 FF")
        cam.send("90 61 04 FF")
        assert await asyncio.wait_for(cancelled, WAIT_S) is True
        with pytest.raises(ViscaCancelledError):
            await asyncio.wait_for(handle.completed(), WAIT_S)
        idle = asyncio.create_task(link.cancel(1, 2))
        assert await cam.expect() == bytes.fromhex("81 22 FF")
        cam.send("90 62 05 FF")
        assert await asyncio.wait_for(idle, WAIT_S) is False


async def test_buffer_full_is_retried_after_a_socket_frees() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        first = link.submit(1, codec_requests.PanTiltHome())
        assert await cam.expect() == HOME
        cam.send("90 41 FF")
        second = link.submit(1, codec_requests.FocusDirect(0x2000))
        assert await cam.expect() == FOCUS
        cam.send("90 60 03 FF")  # buffer full although the link thinks socket 2 is free
        # Resync: the link cancels the socket it believed free, then retries.
        assert await cam.expect() == bytes.fromhex("81 22 FF")
        cam.send("90 62 04 FF")
        assert await cam.expect() == FOCUS
        cam.send("90 42 FF 90 52 FF 90 51 FF")
        await asyncio.wait_for(second.completed(), WAIT_S)
        await asyncio.wait_for(first.completed(), WAIT_S)
        health = link.health()
        assert health.buffer_full_retries == 1
        assert health.resyncs >= 1


async def test_buffer_full_retries_are_bounded() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        task = asyncio.create_task(link.command(1, codec_requests.FocusDirect(0x2000)))
        for _ in range(FAST.buffer_full_retries + 1):
            packet = await cam.expect()
            while packet != FOCUS:  # resync cancels in between
                cam.send(f"90 6{packet[1] & 0x0F} 05 FF")
                packet = await cam.expect()
            cam.send("90 60 03 FF")
        with pytest.raises(ViscaBufferFullError):
            await asyncio.wait_for(task, WAIT_S)


async def test_a0_replies_are_accepted_for_a_single_camera(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        task = asyncio.create_task(link.inquire(1, codec_requests.FocusPositionInquiry()))
        assert await cam.expect() == FOCUS_POS_INQ
        cam.send("A0 50 01 02 03 04 FF")
        assert (await asyncio.wait_for(task, WAIT_S)).counts == 0x1234
        assert "A0" in caplog.text


async def test_silent_camera_times_out_with_named_waits() -> None:
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        with pytest.raises(ViscaTimeoutError) as inquiry:
            await asyncio.wait_for(link.inquire(1, codec_requests.PowerInquiry()), WAIT_S)
        assert inquiry.value.wait == "inquiry reply"
        assert isinstance(inquiry.value, TimeoutError)
        with pytest.raises(ViscaTimeoutError) as command:
            await asyncio.wait_for(link.command(1, codec_requests.FocusDirect(0x2000)), WAIT_S)
        assert command.value.wait == "ACK"
        with pytest.raises(ViscaTimeoutError) as broadcast:
            await asyncio.wait_for(link.ensure_addressed(), WAIT_S)
        assert "AddressSet" in broadcast.value.wait
        assert link.health().timeouts == {"inquiry reply": 1, "ACK": 1, "broadcast reply": 1}
        assert link.connected


async def test_no_byte_stream_crashes_the_link(caplog: pytest.LogCaptureFixture) -> None:
    rng = random.Random(1234)
    alphabet = [0xFF, 0x90, 0xA0, 0x88, 0x41, 0x42, 0x51, 0x52, 0x50, 0x38, 0x60, 0x61, 0x62,
                0x03, 0x04, 0x05, 0x41, 0x30, 0x00, 0x0F, 0x01, 0x02]  # fmt: skip
    caplog.set_level(logging.WARNING)
    async with ScriptedCamera() as cam, ViscaLink(cam.path, timeouts=FAST) as link:
        pending = [
            asyncio.create_task(link.command(1, codec_requests.FocusDirect(0x2000))),
            asyncio.create_task(link.command(1, codec_requests.PanTiltHome())),
            asyncio.create_task(link.inquire(1, codec_requests.VersionInquiry())),
            asyncio.create_task(link.cancel(1, 2)),
        ]
        for _ in range(400):
            size = rng.randint(1, 24)
            if rng.random() < 0.5:
                chunk = bytes(rng.choice(alphabet) for _ in range(size))
            else:
                chunk = rng.randbytes(size)
            cam.send(chunk)
        results = await asyncio.wait_for(
            asyncio.gather(*pending, return_exceptions=True), WAIT_S * 3
        )
        for result in results:
            assert not isinstance(result, BaseException) or isinstance(result, ViscaError)
        assert link.connected
        # Afterwards a well-behaved camera gets a clean answer through. Answer what the noise
        # provoked on the way (cancels after timeouts, re-addressing after a "Network Change").
        cam.send(b"\xff")
        task = asyncio.create_task(link.inquire(1, codec_requests.FocusPositionInquiry()))
        while (packet := await cam.expect()) != FOCUS_POS_INQ:
            if packet[0] == 0x88:
                cam.send(b"\x88\x30\x02\xff" if packet[1] == 0x30 else packet)
            elif packet[1] >> 4 == 0x2:
                cam.send(bytes([0x90, 0x60 | packet[1] & 0x0F, 0x05, 0xFF]))
        cam.send("90 50 01 02 03 04 FF")
        assert (await asyncio.wait_for(task, WAIT_S)).counts == 0x1234
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert link.health().dropped_bytes > 0


async def test_port_that_cannot_be_opened_raises_link_down() -> None:
    link = ViscaLink("/dev/does-not-exist-visca", timeouts=FAST)
    with pytest.raises(LinkDownError, match=r"cannot open .*\(dialout group\)"):
        await link.open()


# ---- recovery, against the simulated camera over a pty --------------------------------------


async def _exercise(camera: object, rng: random.Random, n: int) -> int:
    """Run ``n`` mixed operations; return how many failed (each failure must be typed)."""
    from drivers.visca.camera import Camera

    assert isinstance(camera, Camera)
    failures = 0
    for _ in range(n):
        op = rng.randrange(4)
        try:
            if op == 0:
                await camera.focus_direct(rng.randint(0x1000, 0x8400))
            elif op == 1:
                await camera.focus_position()
            elif op == 2:
                await camera.pan_tilt_absolute(rng.uniform(-5, 5), rng.uniform(-5, 5), 300)
            else:
                await camera.pan_tilt_position()
        except ViscaError:
            failures += 1
    return failures


@pytest.mark.parametrize(
    "spec",
    [
        "seed=1,drop=0.02",
        "seed=2,corrupt=0.02",
        "seed=3,duplicate=0.05",
        "seed=4,delay=0.1:0.3",
        "seed=5,lose_completion=0.2",
        "seed=6,garbage=0.2",
    ],
)
async def test_link_resynchronises_after_faults(spec: str) -> None:
    rng = random.Random(spec)
    # A fast lens and tight move timeouts keep the test short: a lost Completion costs 0.5 s.
    config = DeviceConfig(focus_speed_counts_s=0x7400 / 0.2)
    profile = dataclasses.replace(EVI_D100, focus_full_travel_s=0.2)
    async with sim_camera(config, profile=profile, move_timeout_margin_s=0.25) as (
        server,
        link,
        camera,
    ):
        server.faults.spec = FaultSpec.parse(spec)
        await asyncio.wait_for(_exercise(camera, rng, 15), 60)
        server.faults.spec = FaultSpec()  # the cable is clean again
        await asyncio.sleep(0)
        # Stragglers from the faulty period are dropped, never matched: later commands succeed.
        for target in (0x3000, 0x6000, 0x1800):
            await camera.focus_direct(target)
            assert await camera.focus_position() == target
        await camera.pan_tilt_absolute(3.0, -2.0, 300)
        pan, tilt = await camera.pan_tilt_position()
        assert abs(pan - 3.0) < 0.1
        assert abs(tilt + 2.0) < 0.1
        assert link.connected


async def test_network_change_re_addresses_and_re_initialises() -> None:
    async with sim_camera() as (server, link, camera):
        reinitialised = reinit_event(link)
        server.inject_network_change()
        await asyncio.wait_for(reinitialised.wait(), WAIT_S)
        assert link.health().network_changes == 1
        await camera.focus_direct(0x4000)
        assert await camera.focus_position() == 0x4000


async def test_power_cycle_re_initialises_the_camera() -> None:
    async with sim_camera() as (server, link, camera):
        reinitialised = reinit_event(link)
        server.power_cycle(off_s=0.1)
        await asyncio.wait_for(reinitialised.wait(), WAIT_S)
        # The camera came up in autofocus; re-initialisation put it back to manual.
        assert server.state.autofocus is False
        await camera.focus_direct(0x5000)
        assert await camera.focus_position() == 0x5000


async def test_port_vanishing_and_returning(
    tmp_path: object, caplog: pytest.LogCaptureFixture
) -> None:
    link_path = f"{tmp_path}/visca0"
    async with sim_camera(link_path=link_path) as (server, link, camera):
        reinitialised = reinit_event(link)
        server.close_port()
        with pytest.raises(LinkDownError):
            await camera.focus_position()
        assert not link.connected
        with pytest.raises(LinkDownError, match="reconnecting"):
            await camera.focus_direct(0x3000)
        server.reopen_port()
        await asyncio.wait_for(reinitialised.wait(), WAIT_S)
        assert link.connected
        health = link.health()
        assert health.port_failures == 1
        assert health.reconnects == 1
        assert server.state.autofocus is False  # re-initialised after the power-up
        await camera.focus_direct(0x3000)
        assert await camera.focus_position() == 0x3000
        warnings = [
            r for r in caplog.records if r.levelno == logging.WARNING and "failed" in r.message
        ]
        assert len(warnings) == 1


async def test_requests_during_a_power_cycle_wait_for_re_initialisation() -> None:
    async with sim_camera() as (server, link, camera):
        reinitialised = reinit_event(link)
        server.power_cycle(off_s=0.1)
        # Issued while the camera is dead: the first attempt times out or is failed by the
        # Network Change; the retry is held until the camera is back in manual focus.
        await camera.focus_direct(0x5000)
        assert reinitialised.is_set()
        assert server.state.autofocus is False
        assert await camera.focus_position() == 0x5000


async def test_loop_url_echo_is_not_taken_for_a_reply() -> None:
    async with ViscaLink("loop://", timeouts=FAST) as link:
        with pytest.raises(ViscaTimeoutError):
            await link.inquire(1, codec_requests.PowerInquiry())
        assert link.health().stray_replies == 1  # our own request, echoed


async def test_the_simulated_cameras_link_waits_out_a_late_simulator() -> None:
    # The daemon's simulator answers from a thread of the same process: on a loaded machine its
    # replies come late. The link the daemon opens to it waits them out; the hardware's would not.
    from dffd.config import load_config
    from dffd.daemon.startup import link_timeouts

    sim_waits = link_timeouts(load_config(None))  # the embedded default: the simulated camera
    assert sim_waits is not None
    late = "seed=1,delay=1.0:0.5"  # every reply held 0.5 s
    async with sim_camera(timeouts=sim_waits, retries=0) as (server, link, camera):
        server.faults.spec = FaultSpec.parse(late)
        await camera.focus_direct(0x3000)
        assert await camera.focus_position() == 0x3000
        assert sum(link.health().timeouts.values()) == 0
    async with sim_camera(timeouts=LinkTimeouts(), retries=0) as (server, link, camera):
        server.faults.spec = FaultSpec.parse(late)
        with pytest.raises(ViscaTimeoutError):
            await camera.focus_position()
