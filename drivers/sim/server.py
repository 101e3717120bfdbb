"""Transports for the simulated camera: a real pseudo-terminal, and an in-process form for tests.

:class:`SimCameraServer` serves a :class:`~drivers.sim.device.ViscaDevice` on a pty that pyserial
opens exactly like hardware (both ends raw, the master non-blocking and read with
``loop.add_reader``). With ``link_path`` it keeps a stable symlink to the pty slave, so closing and
reopening the port looks like a USB adapter unplugged and re-plugged under a udev name.

:class:`InProcessCamera` drives the same device in virtual time: feed bytes, advance the clock,
collect what the camera sent and when.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import os
import struct
import termios
import time
import tty
from collections import deque
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Self

from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig, Emission
from drivers.sim.faults import Faults, FaultSpec
from drivers.sim.state import CameraState
from drivers.sim.virtual_clock import VirtualClock
from drivers.visca import codec, codec_framing, codec_requests

logger = logging.getLogger(__name__)

READ_CHUNK = 4096  # bytes per os.read of the pty master; more than a second of 9600 baud
# Bytes the pty would not take yet (nobody reads the slave). A real UART sends into the void; we
# keep a little and then drop the oldest, so a stalled reader cannot make the server grow.
TX_BACKLOG_MAX_BYTES = 8192
# Output nobody has read for this long when a controller writes was meant for nobody (the
# power-up Network Change before anyone opened the port, replies to a controller that has since
# closed it): on a real RS-232 line nobody listens to, those bytes are simply lost. An attached
# controller reads within milliseconds (pyserial blocks in read; its timeout is ~50 ms).
STALE_OUTPUT_S = 0.5
SENT_LOG_MAX = 256  # recent writes remembered to date the unread bytes


class SimCameraServer:
    """The simulated camera on a real pty; use as ``async with SimCameraServer(...) as server``."""

    def __init__(
        self,
        config: DeviceConfig | None = None,
        *,
        faults: Faults | FaultSpec | str | None = None,
        link_path: str | os.PathLike[str] | None = None,
        state: CameraState | None = None,
        stale_output_s: float = STALE_OUTPUT_S,
    ) -> None:
        self.config = config or DeviceConfig()
        self.faults = faults if isinstance(faults, Faults) else Faults(faults)
        self.state = state or CameraState(clock=time.monotonic)
        self.device = ViscaDevice(self.state, self.config, self.faults)
        self.link_path = Path(link_path) if link_path is not None else None
        self._clock = self.state.clock
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_name = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._backlog = bytearray()
        self._writer_armed = False
        self._port_task: asyncio.Task[None] | None = None
        self.dropped_tx_bytes = 0
        self.stale_output_s = stale_output_s
        self.discarded_stale_bytes = 0
        self._sent_log: deque[tuple[float, int]] = deque(maxlen=SENT_LOG_MAX)
        self._stale_timer: asyncio.TimerHandle | None = None
        self.output_discarded = asyncio.Event()  # set whenever stale output was dropped
        self.port_generation = 0  # bumped by every (re)open
        self._generation_waiters: list[tuple[int, asyncio.Future[None]]] = []
        self.faults.bind(self)

    # ---- lifecycle --------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    async def start(self) -> None:
        """Open the pty (and symlink), power the camera up; returns once ``path`` is usable."""
        self._loop = asyncio.get_running_loop()
        self._open_pty()
        self.device.power_up(self._clock())
        self._pump()
        if self.faults.spec.close_port_every is not None:
            self._port_task = asyncio.create_task(self._unplug_periodically())

    async def stop(self) -> None:
        """Stop serving: close the pty, remove the symlink."""
        if self._port_task is not None:
            self._port_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._port_task
            self._port_task = None
        self._close_pty()
        self.faults.bind(None)

    @property
    def path(self) -> str:
        """What pyserial opens: the symlink if ``link_path`` was given, else the pty slave."""
        return str(self.link_path) if self.link_path is not None else self._slave_name

    @property
    def slave_name(self) -> str:
        """The current pty slave device (changes on every reopen)."""
        return self._slave_name

    @property
    def port_open(self) -> bool:
        """True while the pty exists."""
        return self._master is not None

    async def wait_port_generation(self, generation: int) -> None:
        """Return once the pty has been opened ``generation`` times (1 = the first open)."""
        if self.port_generation >= generation:
            return
        assert self._loop is not None, "start the server first"
        future: asyncio.Future[None] = self._loop.create_future()
        self._generation_waiters.append((generation, future))
        try:
            await future
        finally:
            self._generation_waiters = [w for w in self._generation_waiters if w[1] is not future]

    # ---- one-shot faults --------------------------------------------------------------------

    def inject_network_change(self) -> None:
        """Send an unsolicited Network Change now."""
        self.device.inject_network_change(self._clock())
        self._pump()

    def power_cycle(self, off_s: float | None = None) -> None:
        """Cut the camera's power now; it powers up (Network Change) ``off_s`` later."""
        self.device.power_cycle(self._clock(), off_s)
        self._pump()

    def set_silent(self, silent: bool) -> None:
        """While silent the camera reads but never answers."""
        self.device.set_silent(silent)

    def close_port(self) -> None:
        """The port vanishes: pty closed, symlink removed (the driver's reads and writes fail)."""
        if self._master is None:
            return
        self._close_pty()
        self.device.disconnect(self._clock())
        logger.info("sim camera: port closed")

    def reopen_port(self) -> None:
        """A new pty appears (symlink repointed); the camera powers up and sends Network Change."""
        if self._master is not None:
            return
        self._open_pty()
        self.device.reconnect(self._clock())
        self._pump()
        logger.info("sim camera: port reopened at %s", self._slave_name)

    # ---- pty --------------------------------------------------------------------------------

    def _open_pty(self) -> None:
        assert self._loop is not None
        master, slave = os.openpty()
        try:
            # Fully raw on both ends: no echo, no CR/NL translation, no signals (docs/design.md §6).
            tty.setraw(master)
            tty.setraw(slave)
            os.set_blocking(master, False)
            slave_name = os.ttyname(slave)
            if self.link_path is not None:
                tmp = self.link_path.with_name(f".{self.link_path.name}.{os.getpid()}.tmp")
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
                tmp.symlink_to(slave_name)
                tmp.replace(self.link_path)  # atomic: the name never points nowhere while open
        except OSError:
            os.close(master)
            os.close(slave)
            raise
        self._master, self._slave = master, slave
        self._slave_name = slave_name
        self.port_generation += 1
        self._loop.add_reader(master, self._on_readable)
        for wanted, future in self._generation_waiters:
            if wanted <= self.port_generation and not future.done():
                future.set_result(None)
        logger.info("sim camera: serving on %s", self.path)

    def _close_pty(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._stale_timer is not None:
            self._stale_timer.cancel()
            self._stale_timer = None
        self._sent_log.clear()
        if self._master is not None and self._loop is not None:
            self._loop.remove_reader(self._master)
            if self._writer_armed:
                self._loop.remove_writer(self._master)
                self._writer_armed = False
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        self._backlog.clear()
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()

    def _on_readable(self) -> None:
        if self._master is None:
            return
        try:
            data = os.read(self._master, READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # EIO while no slave is open: nothing to read
            logger.debug("sim camera: pty read failed: %s", exc)
            return
        now = self._clock()
        self._discard_stale_output(now)
        self.device.receive(data, now)
        self._pump()

    def _check_stale(self) -> None:
        self._stale_timer = None
        self._discard_stale_output(self._clock())
        if self._sent_log and self._loop is not None:
            # Bytes still unread but younger than the limit: look again when they are not.
            due = self._sent_log[0][0] + self.stale_output_s - self._clock()
            self._stale_timer = self._loop.call_later(max(due, 0.0), self._check_stale)

    def _discard_stale_output(self, now: float) -> None:
        """Drop output still unread in the pty if it waited longer than ``stale_output_s``."""
        if self._slave is None:
            return
        try:
            raw = fcntl.ioctl(self._slave, termios.TIOCINQ, b"\0\0\0\0")
        except OSError:
            return
        unread = struct.unpack("i", raw)[0]
        if unread <= 0:
            self._sent_log.clear()
            return
        # The unread bytes are the last ``unread`` written: find when the oldest of them went.
        counted = 0
        oldest = now
        for when, size in reversed(self._sent_log):
            counted += size
            oldest = when
            if counted >= unread:
                break
        if now - oldest >= self.stale_output_s:
            termios.tcflush(self._slave, termios.TCIFLUSH)
            self.discarded_stale_bytes += unread
            self.output_discarded.set()
            self._sent_log.clear()
            logger.debug("sim camera: discarded %d byte(s) nobody read", unread)

    def _pump(self) -> None:
        """Run the device up to now, write what it sent, and re-arm the timer."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        now = self._clock()
        for emission in self.device.poll(now):
            self._write(emission.data)
        deadline = self.device.next_deadline()
        if deadline is not None and self._loop is not None:
            self._timer = self._loop.call_later(max(0.0, deadline - self._clock()), self._pump)

    def _write(self, data: bytes) -> None:
        if self._master is None:
            return
        self._backlog += data
        self._flush()

    def _flush(self) -> None:
        if self._master is None:
            return
        while self._backlog:
            try:
                written = os.write(self._master, self._backlog)
            except BlockingIOError:
                break
            except OSError as exc:
                logger.debug("sim camera: pty write failed: %s", exc)
                self._backlog.clear()
                break
            del self._backlog[:written]
            self._sent_log.append((self._clock(), written))
            if self._stale_timer is None and self._loop is not None:
                self._stale_timer = self._loop.call_later(self.stale_output_s, self._check_stale)
        if len(self._backlog) > TX_BACKLOG_MAX_BYTES:
            excess = len(self._backlog) - TX_BACKLOG_MAX_BYTES
            del self._backlog[:excess]
            self.dropped_tx_bytes += excess
        assert self._loop is not None
        if self._backlog and not self._writer_armed:
            self._loop.add_writer(self._master, self._flush)
            self._writer_armed = True
        elif not self._backlog and self._writer_armed:
            self._loop.remove_writer(self._master)
            self._writer_armed = False

    async def _unplug_periodically(self) -> None:
        spec = self.faults.spec
        assert spec.close_port_every is not None
        while True:
            await asyncio.sleep(spec.close_port_every)
            self.close_port()
            await asyncio.sleep(spec.close_port_for)
            self.reopen_port()


class InProcessCamera:
    """The simulated camera without a pty, in virtual time: for fast, deterministic unit tests."""

    def __init__(
        self,
        config: DeviceConfig | None = None,
        *,
        faults: Faults | FaultSpec | str | None = None,
        clock: VirtualClock | None = None,
        state: CameraState | None = None,
    ) -> None:
        self.clock = clock or VirtualClock()
        self.config = config or DeviceConfig()
        self.faults = faults if isinstance(faults, Faults) else Faults(faults)
        self.state = state or CameraState(clock=self.clock)
        self.device = ViscaDevice(self.state, self.config, self.faults)
        self.output: deque[Emission] = deque(maxlen=4096)  # everything sent, for inspection
        self._port_open = True
        self.faults.bind(self)
        self.device.power_up(self.clock())

    def now(self) -> float:
        """Current virtual time."""
        return self.clock()

    def send(self, data: bytes | codec_requests.Request) -> None:
        """The controller writes ``data`` (raw bytes, or a request for the current address)."""
        if not isinstance(data, bytes | bytearray):
            data = codec.encode_request(data, self.device.address)
        self.device.receive(bytes(data), self.clock())

    def run_for(self, seconds: float) -> list[Emission]:
        """Advance virtual time by ``seconds``; return what the camera sent meanwhile."""
        return self.run_until(self.clock() + seconds)

    def run_until(
        self, t_end: float, stop: Callable[[list[Emission]], bool] | None = None
    ) -> list[Emission]:
        """Advance to ``t_end`` (or until ``stop(sent so far)`` is true); return what was sent."""
        sent: list[Emission] = []
        while (deadline := self.device.next_deadline()) is not None and deadline <= t_end:
            self.clock.set(max(deadline, self.clock()))
            batch = self.device.poll(self.clock())
            sent += batch
            self.output.extend(batch)
            if stop is not None and batch and stop(sent):
                return sent
        self.clock.set(max(t_end, self.clock()))
        batch = self.device.poll(self.clock())
        sent += batch
        self.output.extend(batch)
        return sent

    def exchange(
        self, data: bytes | codec_requests.Request, within_s: float = 0.1
    ) -> list[Emission]:
        """Send ``data`` and collect everything sent back in the next ``within_s`` seconds."""
        self.send(data)
        return self.run_for(within_s)

    # ---- one-shot faults (FaultTarget) -----------------------------------------------------

    def inject_network_change(self) -> None:
        """Send an unsolicited Network Change now."""
        self.device.inject_network_change(self.clock())

    def power_cycle(self, off_s: float | None = None) -> None:
        """Cut power now; power up ``off_s`` later."""
        self.device.power_cycle(self.clock(), off_s)

    def set_silent(self, silent: bool) -> None:
        """Read but never answer."""
        self.device.set_silent(silent)

    def close_port(self) -> None:
        """The port vanishes."""
        self._port_open = False
        self.device.disconnect(self.clock())

    def reopen_port(self) -> None:
        """The port returns; the camera powers up again."""
        self._port_open = True
        self.device.reconnect(self.clock())


def packets(emissions: list[Emission]) -> list[bytes]:
    """Split emissions into raw packets (garbage dropped), for tests."""
    reassembler = codec_framing.Reassembler()
    out: list[bytes] = []
    for emission in emissions:
        out += reassembler.feed(emission.data)
    return out
