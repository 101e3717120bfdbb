"""The camera port URL, and the same camera API over every transport the simulator serves."""

from __future__ import annotations

import asyncio
import contextlib
import random
import re
import sys
from collections.abc import AsyncIterator
from typing import Any, cast

import pytest

from drivers.sim.device_types import DeviceConfig
from drivers.sim.ip_server import SimUdpServer
from drivers.sim.net_server import SimTcpServer
from drivers.sim.server import SimCameraServer
from drivers.visca.camera import Camera
from drivers.visca.errors import LinkDownError
from drivers.visca.link import ViscaLink
from drivers.visca.transport import UdpTransport
from drivers.visca.url import FORMS, CameraUrl, parse_camera_url
from tests.visca_support import FAST, WAIT_S, reinit_event

# Start-up of `dffd sim-camera` as a subprocess (interpreter + imports) on a loaded machine.
CLI_START_TIMEOUT_S = 20.0


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("/dev/ttyUSB0", CameraUrl("serial", "/dev/ttyUSB0")),
        ("serial:///dev/visca0?baud=9600", CameraUrl("serial", "/dev/visca0", baudrate=9600)),
        ("serial:///dev/visca0", CameraUrl("serial", "/dev/visca0")),
        ("loop://", CameraUrl("serial", "loop://")),
        ("visca-ip://192.168.0.100:52381", CameraUrl("visca-ip", "192.168.0.100", 52381)),
        ("visca-ip://cam.local", CameraUrl("visca-ip", "cam.local", 52381)),
        ("tcp://192.168.0.100:5678", CameraUrl("tcp", "192.168.0.100", 5678)),
        ("TCP://cam", CameraUrl("tcp", "cam", 5678)),
        ("tcp://[::1]:5678", CameraUrl("tcp", "::1", 5678)),
        # pyserial's own URL handlers go to pyserial whole
        ("socket://cam:4001", CameraUrl("serial", "socket://cam:4001")),
        ("rfc2217://cam:2217", CameraUrl("serial", "rfc2217://cam:2217")),
        ("spy:///dev/ttyUSB0", CameraUrl("serial", "spy:///dev/ttyUSB0")),
    ],
)
def test_camera_urls_parse(url: str, expected: CameraUrl) -> None:
    assert parse_camera_url(url) == expected


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("", "empty"),
        ("serial://", "names no device"),
        ("serial:///dev/x?baud=fast", "baud"),
        ("serial:///dev/null?baud=abc", "baud must be a positive integer"),
        ("tcp://:5678", "names no host"),
        ("visca-ip://", "names no host"),
        ("tcp://cam:99999", "1–65535"),
        ("tcp://127.0.0.1:notaport", "1–65535"),
        ("visca-ip://cam:0", "1–65535"),
        # Each of these went to pyserial, which failed only when the link opened.
        ("htp://cam", "unknown scheme 'htp' (did you mean 'tcp://cam'?)"),
        ("http://cam/video.mjpg", "unknown scheme 'http'; use"),
        ("udp://cam:52381", "unknown scheme 'udp' (did you mean 'visca-ip://cam:52381'?)"),
        ("visca_ip://cam", "did you mean 'visca-ip://cam'?"),
        ("visca-ip//192.168.0.100", "no '://' after the scheme (did you mean 'visca-ip://192.1"),
        ("tcp:cam:5678", "did you mean 'tcp://cam:5678'?"),
        ("serial:/dev/ttyUSB0", "did you mean 'serial:///dev/ttyUSB0'?"),
        ("192.168.0.100", "needs a scheme (did you mean 'visca-ip://192.168.0.100' or 'tcp://"),
        ("cam.local:5678", "did you mean 'visca-ip://cam.local:5678' or 'tcp://cam.local:5678'?"),
        ("ttyUSB0", "a serial device is an absolute path"),
        # "dev" would parse as a host and /ttyUSB0 be opened
        ("serial://dev/ttyUSB0", "takes an absolute path (did you mean 'serial:///dev/ttyUSB0'?)"),
    ],
)
def test_bad_camera_urls_say_what_is_wrong(url: str, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)) as info:
        parse_camera_url(url)
    text = str(info.value)
    assert text.startswith(f"{url!r} is not a camera port: ")
    assert text.endswith(f"; use {FORMS}")  # and what a camera port looks like


@contextlib.asynccontextmanager
async def _served(kind: str) -> AsyncIterator[tuple[object, ViscaLink, Camera]]:
    config = DeviceConfig(focus_speed_counts_s=0x7400 / 0.3)
    server: SimCameraServer | SimTcpServer | SimUdpServer
    if kind == "pty":
        server = SimCameraServer(config)
    elif kind == "tcp":
        server = SimTcpServer(config)
    else:
        server = SimUdpServer(config)
    async with server:
        url = server.path if isinstance(server, SimCameraServer) else server.url
        async with ViscaLink(url, timeouts=FAST) as link:
            camera = Camera(link, 1)
            await camera.initialize()
            yield server, link, camera


@pytest.mark.parametrize("kind", ["pty", "tcp", "udp"])
async def test_camera_api_over_every_transport(kind: str) -> None:
    async with _served(kind) as (_, link, camera):
        assert camera.version_info is not None
        assert camera.version_info.vendor == 0x0001
        assert not await camera.focus_is_auto()
        for target in (0x3000, 0x6000):
            await camera.focus_direct(target)
            assert await camera.focus_position() == target
        focus = await camera.start_focus_direct(0x2000)
        move = await camera.start_pan_tilt_absolute(5.0, -3.0, 300)
        assert {await focus.acked(), await move.acked()} == {1, 2}
        await asyncio.wait_for(asyncio.gather(focus.completed(), move.completed()), WAIT_S)
        pan, tilt = await camera.pan_tilt_position()
        assert abs(pan - 5.0) < 0.1
        assert abs(tilt + 3.0) < 0.1
        assert await camera.cancel(2) is False
        health = link.health()
        assert health.timeouts == {}
        assert health.stray_replies == 0


async def test_tcp_link_reconnects_and_re_initialises_after_the_connection_drops() -> None:
    async with _served("tcp") as (server, link, camera):
        assert isinstance(server, SimTcpServer)
        reinitialised = reinit_event(link)
        server.drop_client()
        await asyncio.wait_for(reinitialised.wait(), WAIT_S)
        assert link.health().reconnects == 1
        await camera.focus_direct(0x4000)
        assert await camera.focus_position() == 0x4000


async def test_tcp_port_nobody_listens_on_raises_link_down() -> None:
    async with SimTcpServer() as server:
        url = server.url
    with pytest.raises(LinkDownError, match="cannot connect to the VISCA camera") as exc:
        await ViscaLink(url, timeouts=FAST).open()
    assert "dialout" not in str(exc.value)  # a group for serial devices, not for the network


@pytest.mark.parametrize(("listen", "scheme"), [("tcp", "tcp"), ("udp", "visca-ip")])
async def test_sim_camera_cli_serves_the_network_and_prints_the_address_first(
    listen: str, scheme: str
) -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "dffd", "sim-camera", "--listen", f"{listen}://127.0.0.1:0",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = await asyncio.wait_for(proc.stdout.readline(), CLI_START_TIMEOUT_S)
        url = line.decode().strip()
        assert url.startswith(f"{scheme}://127.0.0.1:")
        async with ViscaLink(url, timeouts=FAST) as link:
            camera = Camera(link, 1)
            version = await camera.initialize()
            assert (version.vendor, version.model) == (0x0001, 0x040D)
    finally:
        proc.terminate()
        assert await asyncio.wait_for(proc.wait(), CLI_START_TIMEOUT_S) == 0


class LossyRelay(asyncio.DatagramProtocol):
    """A UDP relay between driver and camera that loses, duplicates and reorders (seeded)."""

    def __init__(self, target: tuple[str, int], seed: int, rate: float) -> None:
        self.target = target
        self.rng = random.Random(seed)
        self.rate = rate
        self.client: tuple[str, int] | None = None
        self.udp: asyncio.DatagramTransport | None = None
        self.counts = {"relayed": 0, "lost": 0, "duplicated": 0, "delayed": 0}

    async def start(self) -> str:
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: self, local_addr=("127.0.0.1", 0))
        assert self.udp is not None
        return f"visca-ip://127.0.0.1:{self.udp.get_extra_info('sockname')[1]}"

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.udp = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        peer = (addr[0], addr[1])
        if peer != self.target:
            self.client = peer
        to = self.target if peer != self.target else self.client
        if to is None or self.udp is None:
            return
        self.counts["relayed"] += 1
        roll = self.rng.random()
        if roll < self.rate:
            self.counts["lost"] += 1
            return
        copies = 2 if roll < 2 * self.rate else 1
        if copies == 2:
            self.counts["duplicated"] += 1
        for _ in range(copies):
            if self.rng.random() < self.rate:
                # Held back up to ~2 camera fields: overtaken by what follows.
                self.counts["delayed"] += 1
                delay = self.rng.uniform(0.005, 0.035)
                asyncio.get_running_loop().call_later(delay, self._send, data, to)
            else:
                self._send(data, to)

    def _send(self, data: bytes, to: tuple[str, int]) -> None:
        if self.udp is not None and not self.udp.is_closing():
            self.udp.sendto(data, to)


async def test_visca_ip_under_loss_duplication_and_reordering_returns_true_results() -> None:
    config = DeviceConfig(focus_speed_counts_s=0x7400 / 0.3, network_change_at_power_up=False)
    rng = random.Random(12)
    async with SimUdpServer(config) as server:
        relay = LossyRelay(("127.0.0.1", server.port), seed=2024, rate=0.10)
        url = await relay.start()
        try:
            async with ViscaLink(url) as link:
                camera = Camera(link, 1)
                await camera.initialize()
                for _ in range(12):
                    focus = rng.randrange(0x1000, 0x8400)
                    await camera.focus_direct(focus)
                    assert server.state.focus.position(server.state.clock()) == pytest.approx(
                        focus, abs=1
                    )
                    assert await camera.focus_position() == focus
                    pan, tilt = rng.uniform(-20, 20), rng.uniform(-10, 10)
                    await camera.pan_tilt_absolute(pan, tilt, 300)
                    got_pan, got_tilt = await camera.pan_tilt_position()
                    assert abs(got_pan - pan) < 0.1
                    assert abs(got_tilt - tilt) < 0.1
                    assert await camera.focus_is_auto() is False
                stats = cast(UdpTransport, link._transport).channel.stats
                # Lost replies were recovered by retransmission and by restoring ACKs.
                assert stats.retransmits > 0
                assert stats.duplicates > 0
                assert link.health().stray_replies == 0
                # The same counters reach the link's health (what the daemon's status reports).
                ip = link.health().ip
                assert ip is not None
                assert ip.retransmits == stats.retransmits
                assert ip.resets >= 1  # the RESET at connect
        finally:
            assert relay.udp is not None
            relay.udp.close()
    assert min(relay.counts["lost"], relay.counts["duplicated"], relay.counts["delayed"]) > 5
