"""The simulated camera on a TCP port: raw VISCA over TCP, as PTZOptics cameras serve it.

One :class:`~drivers.sim.device.ViscaDevice` in real time; the controller connected last gets
the camera's output. Output while no controller is connected goes nowhere (as on a network
camera), so a controller that connects later reads only replies to its own commands.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from types import TracebackType
from typing import Self

from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import Faults, FaultSpec
from drivers.sim.state import CameraState

logger = logging.getLogger(__name__)

READ_CHUNK = 4096  # bytes per read from the controller's connection


class SimTcpServer:
    """Serve the simulated camera as raw VISCA over TCP on ``host:port`` (0: any free port)."""

    def __init__(
        self,
        config: DeviceConfig | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        faults: Faults | FaultSpec | str | None = None,
        state: CameraState | None = None,
    ) -> None:
        self.config = config or DeviceConfig()
        self.faults = faults if isinstance(faults, Faults) else Faults(faults)
        self.state = state or CameraState(clock=time.monotonic)
        self.device = ViscaDevice(self.state, self.config, self.faults)
        self.host = host
        self.port = port
        self._clock = self.state.clock
        self._server: asyncio.Server | None = None
        self._client: asyncio.StreamWriter | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    @property
    def url(self) -> str:
        """What a controller connects to: ``tcp://host:port``."""
        return f"tcp://{self.host}:{self.port}"

    async def start(self) -> None:
        """Listen, power the camera up."""
        self._server = await asyncio.start_server(self._serve_client, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self.device.power_up(self._clock())
        self._pump()
        logger.info("sim camera: serving raw VISCA on %s", self.url)

    async def stop(self) -> None:
        """Close every connection and stop listening."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._server is not None:
            self._server.close()
        if self._client is not None:
            self._client.close()
            self._client = None
        for task in list(self._tasks):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None

    def drop_client(self) -> None:
        """Close the controller's connection (a network hiccup; the controller reconnects)."""
        if self._client is not None:
            self._client.close()
            self._client = None

    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        if self._client is not None:
            self._client.close()  # one controller at a time: the newest wins
        self._client = writer
        try:
            while data := await reader.read(READ_CHUNK):
                self.device.receive(data, self._clock())
                self._pump()
        except OSError as exc:
            logger.debug("sim camera: TCP controller gone: %s", exc)
        finally:
            if self._client is writer:
                self._client = None
            writer.close()
            if task is not None:
                self._tasks.discard(task)

    def _pump(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for emission in self.device.poll(self._clock()):
            if self._client is not None and not self._client.is_closing():
                self._client.write(emission.data)
        deadline = self.device.next_deadline()
        if deadline is not None:
            delay = max(0.0, deadline - self._clock())
            self._timer = asyncio.get_running_loop().call_later(delay, self._pump)
