"""VISCA test helpers: a scripted camera and a simulated daisy chain, each on a real pty."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
import tty
from collections.abc import AsyncIterator
from types import TracebackType
from typing import Self

from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import Faults
from drivers.sim.server import SimCameraServer
from drivers.sim.state import CameraState
from drivers.visca import codec_framing
from drivers.visca.camera import EVI_D100, Camera, CameraProfile
from drivers.visca.link import ViscaLink
from drivers.visca.session_types import LinkTimeouts

# Bounds on waits in tests: a reply comes within ~1 field; these only cap a test on a loaded
# 2-core machine so that a bug fails the test instead of hanging it.
WAIT_S = 3.0
# Shrunk link timeouts: tests that provoke a timeout should not wait the production 0.3 s
# ten times over, yet a loaded machine must still get replies (1 field + scheduling) in time.
FAST = LinkTimeouts(
    ack_s=0.25,
    inquiry_s=0.25,
    cancel_s=0.25,
    broadcast_s=0.5,
    queue_s=5.0,
    late_reply_guard_s=0.05,
    buffer_full_backoff_s=0.02,
    reconnect_initial_s=0.02,
    reconnect_max_s=0.2,
    reinit_s=5.0,
)


class ScriptedCamera:
    """The camera end of a real pty, played by the test packet by packet."""

    def __init__(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master: int | None = master
        self._slave: int | None = slave
        self.path = os.ttyname(slave)
        self.received: asyncio.Queue[bytes] = asyncio.Queue()
        self._reassembler = codec_framing.Reassembler()

    async def __aenter__(self) -> Self:
        assert self._master is not None
        asyncio.get_running_loop().add_reader(self._master, self._readable)
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close both ends (the driver sees the port vanish)."""
        if self._master is not None:
            asyncio.get_running_loop().remove_reader(self._master)
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    async def expect(self, within_s: float = WAIT_S) -> bytes:
        """The next packet the driver wrote."""
        return await asyncio.wait_for(self.received.get(), within_s)

    def send(self, data: str | bytes) -> None:
        """Write raw bytes (or a hex string) towards the driver."""
        assert self._master is not None
        os.write(self._master, bytes.fromhex(data) if isinstance(data, str) else data)

    def _readable(self) -> None:
        assert self._master is not None
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return
        for raw in self._reassembler.feed(data):
            self.received.put_nowait(raw)


class SimChain:
    """Several simulated cameras daisy-chained on one pty (the sim server serves one device).

    Every device sees every byte; only the last camera's broadcast replies go back (on a real
    chain the earlier cameras relay Address Set and IF_Clear instead of answering them).
    """

    def __init__(self, count: int, config: DeviceConfig | None = None) -> None:
        base = config or DeviceConfig(autofocus_at_power_up=False)
        self.states = [CameraState(clock=time.monotonic) for _ in range(count)]
        self.devices = [
            ViscaDevice(state, _with_address(base, i + 1), Faults())
            for i, state in enumerate(self.states)
        ]
        self._master: int | None = None
        self._slave: int | None = None
        self.path = ""
        self._timer: asyncio.TimerHandle | None = None

    async def __aenter__(self) -> Self:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        now = time.monotonic()
        for device in self.devices:
            device.power_up(now)
        asyncio.get_running_loop().add_reader(master, self._readable)
        self._pump()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._timer is not None:
            self._timer.cancel()
        if self._master is not None:
            asyncio.get_running_loop().remove_reader(self._master)
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None

    def _readable(self) -> None:
        assert self._master is not None
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return
        now = time.monotonic()
        for device in self.devices:
            device.receive(data, now)
        self._pump()

    def _pump(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._master is None:
            return
        now = time.monotonic()
        last = len(self.devices) - 1
        for i, device in enumerate(self.devices):
            for emission in device.poll(now):
                if i != last and emission.data[:1] == b"\x88":
                    continue
                os.write(self._master, emission.data)
        deadlines = [d for device in self.devices if (d := device.next_deadline()) is not None]
        if deadlines:
            delay = max(0.0, min(deadlines) - time.monotonic())
            self._timer = asyncio.get_running_loop().call_later(delay, self._pump)


@contextlib.asynccontextmanager
async def sim_camera(
    config: DeviceConfig | None = None,
    *,
    faults: Faults | str | None = None,
    link_path: str | None = None,
    timeouts: LinkTimeouts = FAST,
    profile: CameraProfile = EVI_D100,
    retries: int = 1,
    move_timeout_margin_s: float = 1.0,
) -> AsyncIterator[tuple[SimCameraServer, ViscaLink, Camera]]:
    """A simulated camera on a pty, a link to it, and an initialised Camera."""
    async with (
        SimCameraServer(config, faults=faults, link_path=link_path) as server,
        ViscaLink(server.path, timeouts=timeouts) as link,
    ):
        camera = Camera(
            link, 1, profile, retries=retries, move_timeout_margin_s=move_timeout_margin_s
        )
        await camera.initialize()
        yield server, link, camera


def reinit_event(link: ViscaLink) -> asyncio.Event:
    """An event set each time the link has re-addressed the chain and re-initialised cameras."""
    event = asyncio.Event()

    async def done() -> None:
        event.set()

    link.add_reinit_callback(done)
    return event


def _with_address(config: DeviceConfig, address: int) -> DeviceConfig:
    from dataclasses import replace

    return replace(config, address=address)
