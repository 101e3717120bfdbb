"""The camera port URL, and the same camera API over every transport the simulator serves."""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import AsyncIterator

import pytest

from drivers.sim.device import DeviceConfig
from drivers.sim.net_server import SimTcpServer
from drivers.sim.server import SimCameraServer
from drivers.visca.camera import Camera
from drivers.visca.errors import LinkDownError
from drivers.visca.link import ViscaLink
from drivers.visca.url import CameraUrl, parse_camera_url
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
        ("tcp://:5678", "names no host"),
        ("tcp://cam:99999", "1–65535"),
        ("visca-ip://cam:0", "1–65535"),
    ],
)
def test_bad_camera_urls_say_what_is_wrong(url: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_camera_url(url)


@contextlib.asynccontextmanager
async def _served(kind: str) -> AsyncIterator[tuple[object, ViscaLink, Camera]]:
    config = DeviceConfig(focus_speed_counts_s=0x7400 / 0.3)
    server: SimCameraServer | SimTcpServer = (
        SimCameraServer(config) if kind == "pty" else SimTcpServer(config)
    )
    async with server:
        url = server.path if isinstance(server, SimCameraServer) else server.url
        async with ViscaLink(url, timeouts=FAST) as link:
            camera = Camera(link, 1)
            await camera.initialize()
            yield server, link, camera


@pytest.mark.parametrize("kind", ["pty", "tcp"])
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
    with pytest.raises(LinkDownError, match="cannot open"):
        await ViscaLink(url, timeouts=FAST).open()


def test_visca_ip_is_refused_with_a_clear_message() -> None:
    with pytest.raises(ValueError, match="not implemented yet"):
        ViscaLink("visca-ip://127.0.0.1:52381")


async def test_sim_camera_cli_serves_tcp_and_prints_the_address_first() -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "dffd", "sim-camera", "--listen", "tcp://127.0.0.1:0",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = await asyncio.wait_for(proc.stdout.readline(), CLI_START_TIMEOUT_S)
        url = line.decode().strip()
        assert url.startswith("tcp://127.0.0.1:")
        async with ViscaLink(url, timeouts=FAST) as link:
            camera = Camera(link, 1)
            version = await camera.initialize()
            assert (version.vendor, version.model) == (0x0001, 0x040D)
    finally:
        proc.terminate()
        assert await asyncio.wait_for(proc.wait(), CLI_START_TIMEOUT_S) == 0
