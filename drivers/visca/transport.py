"""Transports under the VISCA link: a byte pipe to the camera line, opened per connection.

A transport carries whole VISCA packets out (:meth:`Transport.write`, one ``8x … FF`` packet per
call, so a datagram transport can frame each one) and hands whatever arrives to the ``on_data``
callback it was opened with; a transport that breaks calls ``on_lost`` once. Both callbacks run
on the event loop. The link opens a new transport for every (re)connection through a
:data:`TransportFactory`, so a test or a new medium (UDP, TCP) plugs in without touching the
link; :func:`factory_for_url` picks the factory a camera URL (:mod:`drivers.visca.url`) names,
and :func:`open_failure_message` says what to check when it cannot be opened (both moved here
from :mod:`drivers.visca.link`).

:class:`SerialTransport`: a pyserial port read by a dedicated thread, not pyserial-asyncio-fast.
That library registers ``port.fileno()`` with the event loop, which ``loop://`` (and other URL
handlers without a file descriptor) do not have; a reader thread works identically for every
pyserial URL (``/dev/ttyUSB0``, a pty path, ``socket://``, ``loop://``) and turns a vanishing
adapter into one exception in one place. The thread blocks in ``read`` with a short timeout and
hands bytes to the loop with ``call_soon_threadsafe``. Writes (3–16 bytes) go straight from the
loop into the tty driver's buffer, which never blocks without flow control; ``write_timeout``
bounds a wedged port.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import threading
from collections.abc import Awaitable, Callable
from typing import Any, Protocol, cast

import serial

from drivers.visca.ip import IpChannel
from drivers.visca.url import parse_camera_url

logger = logging.getLogger(__name__)

# Reader thread poll period: how quickly close() gets the thread back (cancel_read interrupts
# it on POSIX anyway).
READ_POLL_S = 0.05
# Bound on a write into a wedged port (the tty buffer normally takes 16 bytes at once).
WRITE_TIMEOUT_S = 0.5
# How long close() waits for the reader thread (it wakes within READ_POLL_S).
READER_JOIN_S = 10 * READ_POLL_S

DataCallback = Callable[[bytes], None]
LostCallback = Callable[[BaseException], None]


class Transport(Protocol):
    """One open connection to a VISCA line."""

    def write(self, packet: bytes) -> None:
        """Send one VISCA packet; raise OSError if the line is gone."""
        ...

    async def close(self) -> None:
        """Close the connection (no callback runs afterwards)."""
        ...


# Opens a connection: raise OSError or ValueError when it cannot be opened.
TransportFactory = Callable[[DataCallback, LostCallback], Awaitable[Transport]]


class SerialPortLike(Protocol):
    """The part of ``serial.Serial`` the serial transport uses (a test can pass any object)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes, /) -> int | None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


PortFactory = Callable[[str, int], SerialPortLike]


def open_serial_port(url: str, baudrate: int) -> SerialPortLike:
    """Open ``url`` raw 8N1 at ``baudrate``, no flow control (the default port factory)."""
    port: SerialPortLike = serial.serial_for_url(
        url,
        baudrate=baudrate,
        bytesize=serial.EIGHTBITS,
        parity=serial.PARITY_NONE,
        stopbits=serial.STOPBITS_ONE,
        timeout=READ_POLL_S,
        write_timeout=WRITE_TIMEOUT_S,
        xonxoff=False,
        rtscts=False,
        dsrdtr=False,
    )
    return port


def serial_factory(
    url: str, baudrate: int, port_factory: PortFactory = open_serial_port
) -> TransportFactory:
    """A factory opening :class:`SerialTransport` on ``url`` at ``baudrate``."""
    return functools.partial(SerialTransport.open, url, baudrate, port_factory=port_factory)


class SerialTransport:
    """A serial port (any pyserial URL) with a reader thread feeding the event loop."""

    def __init__(
        self,
        port: SerialPortLike,
        url: str,
        loop: asyncio.AbstractEventLoop,
        on_data: DataCallback,
        on_lost: LostCallback,
    ) -> None:
        self._port = port
        self._url = url
        self._loop = loop
        self._on_data = on_data
        self._on_lost = on_lost
        self._stop = threading.Event()
        self._reader = threading.Thread(
            target=self._reader_main, name=f"visca-reader {url}", daemon=True
        )

    @classmethod
    async def open(
        cls,
        url: str,
        baudrate: int,
        on_data: DataCallback,
        on_lost: LostCallback,
        *,
        port_factory: PortFactory = open_serial_port,
    ) -> SerialTransport:
        """Open the port, flush stale input (bytes from before we opened are not replies)."""
        port = await asyncio.to_thread(port_factory, url, baudrate)
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError):
            port.close()
            raise
        transport = cls(port, url, asyncio.get_running_loop(), on_data, on_lost)
        transport._reader.start()
        return transport

    def write(self, packet: bytes) -> None:
        """Write one packet into the tty buffer (OSError when the port is gone)."""
        if self._stop.is_set():
            raise OSError(f"serial port {self._url} is closed")
        self._port.write(packet)

    async def close(self) -> None:
        """Stop the reader thread and close the port."""
        self._stop.set()
        cancel_read = getattr(self._port, "cancel_read", None)
        if cancel_read is not None:
            with contextlib.suppress(Exception):
                cancel_read()
        if self._reader.is_alive() and self._reader is not threading.current_thread():
            await asyncio.to_thread(self._reader.join, READER_JOIN_S)
        with contextlib.suppress(Exception):
            self._port.close()

    def _reader_main(self) -> None:
        port, stop, loop = self._port, self._stop, self._loop
        while not stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting > 0 else 1)
            except Exception as exc:  # noqa: BLE001 - any failure of the port means it is gone
                if not stop.is_set():
                    with contextlib.suppress(RuntimeError):  # loop already closed
                        loop.call_soon_threadsafe(self._lost, exc)
                return
            if data and not stop.is_set():
                try:
                    loop.call_soon_threadsafe(self._data, data)
                except RuntimeError:
                    return

    def _data(self, data: bytes) -> None:
        if not self._stop.is_set():
            self._on_data(data)

    def _lost(self, exc: BaseException) -> None:
        if not self._stop.is_set():
            self._on_lost(exc)


# Connecting to a network camera: a LAN answers in milliseconds; this bounds a dead host.
TCP_CONNECT_TIMEOUT_S = 3.0
# Closing a TCP connection: the FIN handshake on a LAN; bounded so close() never hangs.
TCP_CLOSE_TIMEOUT_S = 1.0
TCP_READ_CHUNK = 4096


class TcpTransport:
    """Raw VISCA over TCP (PTZOptics style): the serial byte stream in a TCP connection."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        on_data: DataCallback,
        on_lost: LostCallback,
    ) -> None:
        self._reader = reader
        self._writer = writer
        self._on_data = on_data
        self._on_lost = on_lost
        self._closed = False
        self._task = asyncio.get_running_loop().create_task(self._read(), name="visca tcp read")

    @classmethod
    async def open(
        cls, host: str, port: int, on_data: DataCallback, on_lost: LostCallback
    ) -> TcpTransport:
        """Connect to ``host:port`` (OSError/TimeoutError when it cannot)."""
        async with asyncio.timeout(TCP_CONNECT_TIMEOUT_S):
            reader, writer = await asyncio.open_connection(host, port)
        return cls(reader, writer, on_data, on_lost)

    def write(self, packet: bytes) -> None:
        """Queue one packet on the connection (OSError once it is closed)."""
        if self._closed or self._writer.is_closing():
            raise OSError("VISCA TCP connection is closed")
        self._writer.write(packet)

    async def close(self) -> None:
        """Close the connection and stop reading."""
        self._closed = True
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._writer.close()
        with contextlib.suppress(OSError, TimeoutError):
            async with asyncio.timeout(TCP_CLOSE_TIMEOUT_S):
                await self._writer.wait_closed()

    async def _read(self) -> None:
        try:
            while data := await self._reader.read(TCP_READ_CHUNK):
                if not self._closed:
                    self._on_data(data)
            error: BaseException = ConnectionResetError("the camera closed the connection")
        except OSError as exc:
            error = exc
        if not self._closed:
            self._on_lost(error)


def tcp_factory(host: str, port: int) -> TransportFactory:
    """A factory opening :class:`TcpTransport` to ``host:port``."""
    return functools.partial(TcpTransport.open, host, port)


class UdpTransport(asyncio.DatagramProtocol):
    """VISCA over IP: each VISCA packet in a Sony-framed UDP datagram (:mod:`drivers.visca.ip`).

    The sans-IO :class:`~drivers.visca.ip.IpChannel` does the framing, sequencing, retransmission
    and reply matching; this class gives it a socket and a timer, and hands the VISCA bytes it
    recovers to ``on_data``. UDP has no connection to lose: a dead camera shows as the session's
    timeouts, and ICMP errors (port unreachable) are only logged.
    """

    def __init__(self, on_data: DataCallback, on_lost: LostCallback, channel: IpChannel) -> None:
        self._on_data = on_data
        self._on_lost = on_lost
        self.channel = channel
        self._udp: asyncio.DatagramTransport | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False

    @classmethod
    async def open(
        cls,
        host: str,
        port: int,
        on_data: DataCallback,
        on_lost: LostCallback,
        *,
        channel: IpChannel | None = None,
    ) -> UdpTransport:
        """Open a UDP socket towards ``host:port`` and RESET the camera's sequence."""
        loop = asyncio.get_running_loop()
        proto = cls(on_data, on_lost, channel or IpChannel())
        async with asyncio.timeout(TCP_CONNECT_TIMEOUT_S):  # name resolution only
            await loop.create_datagram_endpoint(lambda: proto, remote_addr=(host, port))
        proto.channel.connection_made(loop.time())
        proto._flush()
        return proto

    # asyncio.DatagramProtocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # 3.11's selector datagram transport does not subclass DatagramTransport.
        self._udp = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        if self._closed:
            return
        self.channel.receive(data, asyncio.get_running_loop().time())
        self._flush()

    def error_received(self, exc: Exception) -> None:
        logger.debug("VISCA over IP: %s (retransmission continues)", exc)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._closed:
            self._closed = True
            self._on_lost(exc or ConnectionResetError("the UDP socket closed"))

    # Transport

    def write(self, packet: bytes) -> None:
        """Hand one VISCA packet to the channel (OSError once closed or when its queue is full)."""
        if self._closed or self._udp is None:
            raise OSError("VISCA-over-IP socket is closed")
        self.channel.send(packet, asyncio.get_running_loop().time())
        self._flush()

    async def close(self) -> None:
        """Close the socket; no callback runs afterwards."""
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._udp is not None:
            self._udp.close()

    def _flush(self) -> None:
        udp = self._udp
        if udp is not None and not self._closed:
            for datagram in self.channel.datagrams_to_send():
                udp.sendto(datagram)
        data = self.channel.data_received()
        if data and not self._closed:
            self._on_data(data)
        self._rearm()

    def _rearm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        deadline = self.channel.next_deadline()
        if deadline is None or self._closed:
            return
        loop = asyncio.get_running_loop()
        self._timer = loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        if self._closed:
            return
        self.channel.poll(asyncio.get_running_loop().time())
        self._flush()


def udp_factory(host: str, port: int) -> TransportFactory:
    """A factory opening :class:`UdpTransport` (VISCA over IP) to ``host:port``."""

    async def open_udp(on_data: DataCallback, on_lost: LostCallback) -> Transport:
        return await UdpTransport.open(host, port, on_data, on_lost)

    return open_udp


# --------------------------------------------------------------------------------------------
# The transport a camera URL names
# --------------------------------------------------------------------------------------------


def factory_for_url(url: str, baudrate: int, port_factory: PortFactory) -> TransportFactory:
    """The transport ``url`` names (see drivers.visca.url); ValueError for a bad URL."""
    parsed = parse_camera_url(url)
    if parsed.transport == "tcp":
        assert parsed.port is not None
        return tcp_factory(parsed.target, parsed.port)
    if parsed.transport == "visca-ip":
        assert parsed.port is not None
        return udp_factory(parsed.target, parsed.port)
    return serial_factory(parsed.target, parsed.baudrate or baudrate, port_factory)


def open_failure_message(url: str, baudrate: int, exc: BaseException) -> str:
    """What went wrong opening ``url`` and what to check: the device for a serial port (the
    dialout group grants access to it), the camera's address and network for VISCA over IP."""
    try:
        parsed = parse_camera_url(url)
    except ValueError:
        return f"cannot open VISCA port {url!r}: {exc}"
    if parsed.transport == "serial":
        return (
            f"cannot open VISCA port {url!r} at {baudrate} baud: {exc}; check that the device "
            "exists, is not in use, and that you may open it (dialout group)"
        )
    return (
        f"cannot connect to the VISCA camera at {url!r} ({parsed.transport}): {exc}; check that "
        "the camera is on, its address and port are right, and the network reaches it"
    )
