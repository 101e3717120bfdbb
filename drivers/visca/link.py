"""Asyncio VISCA link over pyserial: framing, per-socket reply matching, queueing, recovery.

One :class:`ViscaLink` owns one serial port, which may carry a daisy chain of up to seven cameras.
For each camera address it keeps

* a bounded command queue and at most two commands in flight (the camera's two sockets; one if
  its VersionInq says so). A command is written only when no earlier command to the same camera
  still waits for its ACK, so the ACK (or error) that comes back belongs to exactly one command,
  and from then on its Completion is matched by *socket*: a Completion for a socket the link no
  longer has a command in (late, after a timeout) is counted and dropped, never given to another
  command;
* inquiries, one outstanding at a time, matched in order (they are answered without ACK, even
  while both sockets are busy); a reply whose data does not parse for the outstanding inquiry is
  a straggler and is dropped;
* pending Cancels per socket (``z0 6p 04``: cancelled; ``z0 6p 05``: the socket was idle).

Stops (Pan-tiltDrive stop, Focus Stop) and Cancels jump the queue. An unexpected buffer-full is
recovered by waiting for a socket to free (bounded retries) and, if the link believes a socket is
free that the camera says is not, cancelling it (a resync). A Network Change fails every waiter
with :class:`ViscaNetworkChangeError`, re-addresses the chain (Address Set + IF_Clear) and runs the
re-initialisation callbacks. A port that vanishes fails every waiter with :class:`LinkDownError`,
is reopened with capped exponential backoff, re-addressed, and the callbacks run again.

Every wait is bounded by a named timeout (:class:`LinkTimeouts`), armed by the link itself as a
timer on each state change, so a caller's future always resolves.

Transport: a pyserial port read by a dedicated thread, not pyserial-asyncio-fast. That library
registers ``port.fileno()`` with the event loop, which ``loop://`` (and other URL handlers without a
file descriptor) do not have; a reader thread works identically for every pyserial URL
(``/dev/ttyUSB0``, a pty path, ``socket://``, ``loop://``) and turns a vanishing adapter into one
exception in one place. The thread blocks in ``read`` with a short timeout and hands bytes to the
loop with ``call_soon_threadsafe``. Writes (3–16 bytes) go straight from the loop into the tty
driver's buffer, which never blocks without flow control; ``write_timeout`` bounds a wedged port.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, cast

import serial

from drivers.visca.codec import (
    BROADCAST_ADDRESS,
    CONTROLLER_ADDRESS,
    MAX_CAMERA_ADDRESS,
    MIN_CAMERA_ADDRESS,
    Ack,
    AddressSet,
    AddressSetReply,
    Broadcast,
    BroadcastEcho,
    CamPower,
    Cancel,
    CodecError,
    Command,
    Completion,
    ErrorCode,
    ErrorReply,
    FocusDirect,
    FocusDirection,
    FocusDrive,
    FocusOnePush,
    IFClearBroadcast,
    Inquiry,
    InquiryData,
    InquiryReply,
    NetworkChange,
    Packet,
    PanDirection,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltHome,
    PanTiltRelative,
    PanTiltReset,
    Reassembler,
    Reply,
    Request,
    TiltDirection,
    ZoomDirect,
    check_range,
    decode_reply,
    encode_request,
)
from drivers.visca.errors import (
    LinkBusyError,
    LinkDownError,
    ViscaError,
    ViscaNetworkChangeError,
    ViscaTimeoutError,
    error_from_reply,
)

logger = logging.getLogger(__name__)

TRACE = 5  # raw bytes on the wire; below DEBUG (parsed packets)
logging.addLevelName(TRACE, "TRACE")

# ---- Named timings (seconds) -------------------------------------------------------------------
# A camera handles one message per video field (16.7 ms at 60 Hz, 20 ms at 50 Hz) and the wire
# carries 960 bytes/s at 9600 baud: a 16-byte command plus a 3-byte ACK is ~20 ms, so an answer
# is due ~40 ms after the write when the camera is idle, ~90 ms when it also has two commands
# and an inquiry to take in. The defaults leave a margin of ~3x over that for OS scheduling and
# USB-serial latency (FTDI latency timer 16 ms per direction).
FIELD_S = 1 / 60  # one video field at 60 Hz: the camera takes one message per field
ACK_TIMEOUT_S = 0.3
INQUIRY_TIMEOUT_S = 0.3
CANCEL_TIMEOUT_S = 0.3
# Address Set and broadcast IF_Clear are relayed by every camera of the chain (up to 7), each
# after taking it in: 7 x (1 field + 5 bytes) ~ 0.18 s, plus margin.
BROADCAST_TIMEOUT_S = 1.0
# Longest a command may wait in the queue for a free socket: longer than the longest Completion
# timeout of a normal move below, so a queued command outlives the moves ahead of it.
QUEUE_TIMEOUT_S = 30.0
# After an ACK or inquiry timeout the answer may still be on its way; hold the next request of
# that kind this long so a straggler cannot be taken for the next request's answer (~6 fields).
LATE_REPLY_GUARD_S = 0.1
# Buffer full (a third command while two run) is never provoked by the link; if one comes
# (another controller, a lost ACK left a "ghost" command running), retry after a socket frees or
# after this pause (~3 fields), at most BUFFER_FULL_RETRIES times.
BUFFER_FULL_BACKOFF_S = 0.05
BUFFER_FULL_RETRIES = 3
# Reconnect backoff when the port vanished: first retry quickly (a USB re-enumeration takes
# ~0.1–1 s), then double up to a cap that keeps a replugged adapter in use within seconds.
RECONNECT_INITIAL_S = 0.1
RECONNECT_MAX_S = 5.0
# Re-initialising one camera (Address Set, IF_Clear, power-on, version, focus mode) after a
# reconnect or Network Change; power-on alone takes up to POWER_COMPLETION_TIMEOUT_S.
REINIT_TIMEOUT_S = 30.0
# Reader thread poll period: how quickly close() gets the thread back (cancel_read interrupts
# it on POSIX anyway).
READ_POLL_S = 0.05
# Bound on a write into a wedged port (the tty buffer normally takes 16 bytes at once).
WRITE_TIMEOUT_S = 0.5

# Completion timeouts per command kind (the camera layer passes move-specific values).
# Focus Direct end to end takes ~2 s worst case on the EVI-D100 lens; Zoom Direct wide to tele
# ~2.5 s; Pan-tiltDrive and Focus Far/Near/Stop complete almost at once (the motion continues);
# One Push AF hunts for up to ~3 s; Home crosses at most half the pan range at high speed;
# Reset runs to both end stops and back; power-on initialises the pan/tilt mechanics (~7 s on
# the EVI-D70, whose manual gives it).
FOCUS_DIRECT_COMPLETION_TIMEOUT_S = 3.0
ZOOM_DIRECT_COMPLETION_TIMEOUT_S = 4.0
DRIVE_COMPLETION_TIMEOUT_S = 1.0
ONE_PUSH_AF_COMPLETION_TIMEOUT_S = 6.0
HOME_COMPLETION_TIMEOUT_S = 5.0
RESET_COMPLETION_TIMEOUT_S = 15.0
POWER_COMPLETION_TIMEOUT_S = 15.0
# Absolute/relative moves: the camera layer computes distance / speed; this is the fallback.
PAN_TILT_MOVE_COMPLETION_TIMEOUT_S = 20.0

# Set inside the re-initialisation task: its requests pass the gate that holds everyone else's.
_REINIT_CONTEXT: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "visca_reinit", default=False
)

COMMAND_QUEUE_MAX = 16  # per camera; a caller issuing faster than the camera runs gets an error
INQUIRY_QUEUE_MAX = 16  # per camera
SOCKETS_PER_CAMERA = 2


@dataclass(frozen=True, slots=True)
class LinkTimeouts:
    """Every wait of the link, in seconds (defaults: the module constants; tests shrink them)."""

    ack_s: float = ACK_TIMEOUT_S
    inquiry_s: float = INQUIRY_TIMEOUT_S
    cancel_s: float = CANCEL_TIMEOUT_S
    broadcast_s: float = BROADCAST_TIMEOUT_S
    queue_s: float = QUEUE_TIMEOUT_S
    late_reply_guard_s: float = LATE_REPLY_GUARD_S
    buffer_full_backoff_s: float = BUFFER_FULL_BACKOFF_S
    buffer_full_retries: int = BUFFER_FULL_RETRIES
    reconnect_initial_s: float = RECONNECT_INITIAL_S
    reconnect_max_s: float = RECONNECT_MAX_S
    reinit_s: float = REINIT_TIMEOUT_S
    completion_scale: float = 1.0  # multiplies every default Completion timeout

    def completion_s(self, request: Command) -> float:
        """Default Completion timeout for ``request`` (scaled by ``completion_scale``)."""
        return _default_completion_s(request) * self.completion_scale


@dataclass(frozen=True, slots=True)
class LinkHealth:
    """A snapshot of the link's counters (all monotonic since the link was created)."""

    url: str
    connected: bool
    bytes_in: int
    bytes_out: int
    packets_in: int
    packets_out: int
    replies: dict[str, int]
    errors_by_code: dict[int, int]
    timeouts: dict[str, int]
    dropped_bytes: int
    bad_packets: int
    stray_replies: int
    lost_completions: int
    resyncs: int
    buffer_full_retries: int
    network_changes: int
    reconnects: int
    port_failures: int
    last_reply_monotonic: float | None
    chain_length: int | None


class SerialPortLike(Protocol):
    """The part of ``serial.Serial`` the link uses (a test can pass any object with these)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes, /) -> int | None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


AnswerT_co = TypeVar("AnswerT_co", bound=InquiryData, covariant=True)
AnswerT = TypeVar("AnswerT", bound=InquiryData)


class InquiryLike(Protocol[AnswerT_co]):
    """An inquiry of the codec: ``to_message`` frames it, ``parse_reply`` types its answer."""

    def to_message(self) -> bytes: ...

    def parse_reply(self, data: bytes) -> AnswerT_co: ...


PortFactory = Callable[[str, int], SerialPortLike]
ReinitCallback = Callable[[], Awaitable[None]]


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


class CommandHandle:
    """A command submitted to the link: await its ACK (socket) and its Completion separately."""

    def __init__(self, link: ViscaLink, entry: _CommandEntry) -> None:
        self._link = link
        self._entry = entry

    @property
    def request(self) -> Command:
        """The command."""
        return self._entry.request

    @property
    def address(self) -> int:
        """The camera address."""
        return self._entry.address

    @property
    def socket(self) -> int | None:
        """The socket the camera put the command in (None before its ACK)."""
        return self._entry.socket

    def done(self) -> bool:
        """True once the command completed or failed."""
        return self._entry.done.done()

    async def acked(self) -> int:
        """Wait for the ACK and return the socket; raise the command's error if it failed."""
        return cast(int, await self._link._await_entry(self._entry, self._entry.acked))

    async def completed(self) -> None:
        """Wait for the Completion; raise ViscaErrorReply/ViscaTimeoutError/LinkDownError."""
        await self._link._await_entry(self._entry, self._entry.done)


class ViscaLink:
    """The controller side of one VISCA serial line (one or more cameras on a daisy chain)."""

    def __init__(
        self,
        url: str,
        baudrate: int = 9600,
        *,
        timeouts: LinkTimeouts | None = None,
        port_factory: PortFactory = open_serial_port,
    ) -> None:
        self.url = url
        self.baudrate = baudrate
        self.timeouts = timeouts or LinkTimeouts()
        self._port_factory = port_factory
        self._port: SerialPortLike | None = None
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()
        self._generation = 0  # bumps on every (re)open: bytes from an old port are ignored
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reassembler = Reassembler()
        self._cameras: dict[int, _CameraState] = {}
        self._broadcasts: deque[_BroadcastEntry] = deque()
        self._broadcast_lock = asyncio.Lock()
        self._address_lock = asyncio.Lock()
        self._addressed = False
        # Closed from a Network Change or reconnect until the chain is re-addressed and the
        # cameras re-initialised: only the re-initialisation's own requests go out meanwhile
        # (a user's retried Focus Direct must not reach a camera still in autofocus, nor be
        # wiped by the re-initialisation's IF_Clear).
        self._gated = False
        self._closing = False
        self._connected = False
        self._down_reported = False
        self._reinit_callbacks: list[ReinitCallback] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._reconnect_task: asyncio.Task[None] | None = None
        self._reinit_task: asyncio.Task[None] | None = None
        self._reinit_requests = 0  # bumped per reason to re-initialise; a running pass restarts
        self._aliased_warned = False
        self.chain_length: int | None = None
        # counters
        self._bytes_in = 0
        self._bytes_out = 0
        self._packets_in = 0
        self._packets_out = 0
        self._replies: Counter[str] = Counter()
        self._errors: Counter[int] = Counter()
        self._timeouts: Counter[str] = Counter()
        self._bad_packets = 0
        self._stray = 0
        self._lost_completions = 0
        self._resyncs = 0
        self._buffer_full_retries = 0
        self._network_changes = 0
        self._reconnects = 0
        self._port_failures = 0
        self._last_reply: float | None = None

    # ---- lifecycle --------------------------------------------------------------------------

    async def open(self) -> None:
        """Open the port (flushing stale input); raise LinkDownError if it cannot be opened."""
        self._loop = asyncio.get_running_loop()
        self._closing = False
        try:
            await self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkDownError(
                f"cannot open VISCA port {self.url!r} at {self.baudrate} baud: {exc}; check "
                "that the device exists, is not in use, and that you may open it (dialout group)"
            ) from exc

    async def close(self) -> None:
        """Stop background tasks, fail every waiter with LinkDownError, close the port."""
        self._closing = True
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._fail_everything(LinkDownError(f"VISCA link {self.url!r} was closed"))
        await self._close_port()
        self._connected = False

    async def __aenter__(self) -> ViscaLink:
        await self.open()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        """True while the port is open."""
        return self._connected

    def add_reinit_callback(self, callback: ReinitCallback) -> None:
        """Run ``callback`` after the chain was re-addressed (reconnect, Network Change)."""
        if callback not in self._reinit_callbacks:
            self._reinit_callbacks.append(callback)

    def remove_reinit_callback(self, callback: ReinitCallback) -> None:
        """Forget a callback added with :meth:`add_reinit_callback`."""
        with contextlib.suppress(ValueError):
            self._reinit_callbacks.remove(callback)

    def set_max_sockets(self, address: int, sockets: int) -> None:
        """Limit commands in flight for ``address`` (VersionInq's KK; 1 or 2)."""
        check_range("max sockets", sockets, 1, SOCKETS_PER_CAMERA)
        self._camera(address).max_sockets = sockets

    def health(self) -> LinkHealth:
        """Counters and state for status reporting."""
        return LinkHealth(
            url=self.url,
            connected=self._connected,
            bytes_in=self._bytes_in,
            bytes_out=self._bytes_out,
            packets_in=self._packets_in,
            packets_out=self._packets_out,
            replies=dict(self._replies),
            errors_by_code=dict(self._errors),
            timeouts=dict(self._timeouts),
            dropped_bytes=self._reassembler.dropped_bytes,
            bad_packets=self._bad_packets,
            stray_replies=self._stray,
            lost_completions=self._lost_completions,
            resyncs=self._resyncs,
            buffer_full_retries=self._buffer_full_retries,
            network_changes=self._network_changes,
            reconnects=self._reconnects,
            port_failures=self._port_failures,
            last_reply_monotonic=self._last_reply,
            chain_length=self.chain_length,
        )

    def running(self, address: int) -> dict[int, Command]:
        """Commands in flight for ``address`` by socket (as the link believes)."""
        cam = self._cameras.get(address)
        return {} if cam is None else {s: e.request for s, e in cam.sockets.items()}

    # ---- requests -----------------------------------------------------------------------------

    def submit(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> CommandHandle:
        """Queue ``command`` for camera ``address`` and return its handle (nothing awaited yet).

        ``priority`` puts it at the head of the queue (default: True for Stop commands).
        """
        self._require_up()
        cam = self._camera(address)
        if command.KIND != "command":
            raise TypeError(f"{type(command).__name__} is not a command (use inquire/broadcast)")
        if len(cam.queue) >= COMMAND_QUEUE_MAX:
            raise LinkBusyError(
                f"{len(cam.queue)} commands already queued for camera {address}: wait for "
                "earlier commands to complete before issuing more"
            )
        if priority is None:
            priority = is_stop(command)
        timeout = (
            completion_timeout
            if completion_timeout is not None
            else self.timeouts.completion_s(command)
        )
        entry = _CommandEntry(
            address=address,
            request=command,
            completion_timeout=timeout,
            acked=self._future(),
            done=self._future(),
            privileged=_REINIT_CONTEXT.get(),
        )
        if priority:
            cam.queue.appendleft(entry)
        else:
            cam.queue.append(entry)
        entry.timer = self._call_later(self.timeouts.queue_s, self._on_queue_timeout, cam, entry)
        logger.debug("camera %d: queued %s (priority=%s)", address, entry.name, priority)
        self._pump(cam)
        return CommandHandle(self, entry)

    async def command(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> None:
        """Send ``command`` and return on its Completion (raise on error or timeout)."""
        handle = self.submit(
            address, command, priority=priority, completion_timeout=completion_timeout
        )
        await handle.completed()

    async def inquire(self, address: int, inquiry: InquiryLike[AnswerT]) -> AnswerT:
        """Send ``inquiry`` and return its typed answer (``inquiry.parse_reply``)."""
        self._require_up()
        cam = self._camera(address)
        if getattr(inquiry, "KIND", None) != "inquiry":
            raise TypeError(f"{type(inquiry).__name__} is not an inquiry")
        if len(cam.inquiries) >= INQUIRY_QUEUE_MAX:
            raise LinkBusyError(
                f"{len(cam.inquiries)} inquiries already queued for camera {address}: "
                "poll less often"
            )
        entry = _InquiryEntry(
            address=address,
            request=cast(Inquiry, inquiry),
            result=self._future(),
            privileged=_REINIT_CONTEXT.get(),
        )
        cam.inquiries.append(entry)
        entry.timer = self._call_later(
            self.timeouts.queue_s, self._on_inquiry_queue_timeout, cam, entry
        )
        self._pump(cam)
        return cast(AnswerT, await self._await_entry(entry, entry.result))

    async def cancel(self, address: int, socket: int) -> bool:
        """Cancel the command in ``socket``; True if one was cancelled, False if it was idle."""
        self._require_up()
        check_range("socket", socket, 1, SOCKETS_PER_CAMERA)
        cam = self._camera(address)
        pending = cam.cancels.get(socket)
        if pending is None:
            pending = self._send_cancel(cam, socket)
        return await asyncio.shield(pending.result)

    async def broadcast(self, request: Broadcast) -> Reply:
        """Send a broadcast (Address Set, IF_Clear) and return the packet that came back."""
        self._require_up()
        async with self._broadcast_lock:
            entry = _BroadcastEntry(request=request, result=self._future())
            self._broadcasts.append(entry)
            try:
                entry.timer = self._call_later(
                    self.timeouts.broadcast_s, self._on_broadcast_timeout, entry
                )
                self._write(encode_request(request, BROADCAST_ADDRESS), type(request).__name__)
                return await asyncio.shield(entry.result)
            finally:
                self._cancel_timer(entry)
                with contextlib.suppress(ValueError):
                    self._broadcasts.remove(entry)

    async def ensure_addressed(self, *, force: bool = False) -> int:
        """Address Set + IF_Clear (broadcast) once per connection; return the chain length."""
        async with self._address_lock:
            if self._addressed and not force and self.chain_length is not None:
                return self.chain_length
            reply = await self.broadcast(AddressSet())
            if not isinstance(reply, AddressSetReply):  # pragma: no cover - matched by type
                raise ViscaError(f"Address Set answered by {reply!r}")
            self.chain_length = reply.next_address - 1
            await self.broadcast(IFClearBroadcast())
            self._addressed = True
            logger.info("VISCA chain on %s addressed: %d camera(s)", self.url, self.chain_length)
            return self.chain_length

    # ---- internals: waiting -----------------------------------------------------------------

    async def _await_entry(self, entry: _Entry, fut: asyncio.Future[Any]) -> Any:
        # The link's own timers resolve every future; shield so a cancelled caller does not
        # cancel the future the link still needs to match replies against.
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            self._abandon(entry)
            raise

    def _abandon(self, entry: _Entry) -> None:
        """The caller went away: drop a queued request; an in-flight one still consumes replies."""
        cam = self._cameras.get(entry.address)
        if cam is None:
            return
        if isinstance(entry, _CommandEntry) and entry in cam.queue:
            cam.queue.remove(entry)
            self._cancel_timer(entry)
        elif isinstance(entry, _InquiryEntry) and entry in cam.inquiries:
            cam.inquiries.remove(entry)
            self._cancel_timer(entry)

    # ---- internals: sending -------------------------------------------------------------------

    def _pump(self, cam: _CameraState) -> None:
        """Write whatever may be written now for ``cam``."""
        if not self._connected or self._closing:
            return
        now = time.monotonic()
        inquiry = self._eligible(cam.inquiries)
        if cam.inquiry_pending is None and inquiry is not None:
            if now < cam.inquiry_guard_until:
                self._schedule_pump(cam, cam.inquiry_guard_until - now)
            else:
                cam.inquiries.remove(inquiry)
                self._cancel_timer(inquiry)
                cam.inquiry_pending = inquiry
                cam.first_reply.append(inquiry)
                inquiry.timer = self._call_later(
                    self.timeouts.inquiry_s, self._on_inquiry_timeout, cam, inquiry
                )
                if not self._send(inquiry.address, inquiry.request, inquiry.name):
                    return
        entry = self._eligible(cam.queue)
        if (
            cam.awaiting_ack is None
            and entry is not None
            and len(cam.sockets) < cam.max_sockets
            and cam.hold is None
        ):
            if now < cam.command_guard_until:
                self._schedule_pump(cam, cam.command_guard_until - now)
                return
            cam.queue.remove(entry)
            self._cancel_timer(entry)
            cam.awaiting_ack = entry
            cam.first_reply.append(entry)
            entry.timer = self._call_later(self.timeouts.ack_s, self._on_ack_timeout, cam, entry)
            self._send(entry.address, entry.request, entry.name)

    def _eligible(self, entries: deque[EntryT]) -> EntryT | None:
        """The next entry that may go now (while gated: the first re-initialisation request)."""
        if not self._gated:
            return entries[0] if entries else None
        return next((e for e in entries if e.privileged), None)

    def _schedule_pump(self, cam: _CameraState, delay: float) -> None:
        if cam.pump_timer is None:
            cam.pump_timer = self._call_later(delay, self._delayed_pump, cam)

    def _delayed_pump(self, cam: _CameraState) -> None:
        cam.pump_timer = None
        self._pump(cam)

    def _send(self, address: int, request: Request, name: str) -> bool:
        try:
            self._write(encode_request(request, address), name)
        except LinkDownError:
            return False
        return True

    def _write(self, data: bytes, what: str) -> None:
        port = self._port
        if port is None or not self._connected:
            raise LinkDownError(self._down_message())
        try:
            port.write(data)
        except (serial.SerialException, OSError) as exc:
            self._on_port_failure(self._generation, exc)
            raise LinkDownError(self._down_message()) from exc
        self._bytes_out += len(data)
        self._packets_out += 1
        logger.log(TRACE, "%s >> %s", self.url, data.hex(" "))
        logger.debug("sent %s: %s", what, data.hex(" "))

    def _send_cancel(self, cam: _CameraState, socket: int) -> _CancelEntry:
        entry = _CancelEntry(address=cam.address, socket=socket, result=self._future())
        cam.cancels[socket] = entry
        entry.timer = self._call_later(self.timeouts.cancel_s, self._on_cancel_timeout, cam, entry)
        self._send(cam.address, Cancel(socket), entry.name)
        return entry

    # ---- internals: receiving -----------------------------------------------------------------

    def _on_bytes(self, generation: int, data: bytes) -> None:
        if generation != self._generation or self._closing:
            return
        self._bytes_in += len(data)
        logger.log(TRACE, "%s << %s", self.url, data.hex(" "))
        dropped_before = self._reassembler.dropped_bytes
        for raw in self._reassembler.feed(data):
            try:
                self._on_packet(raw)
            except Exception:  # a bug in matching must not kill the reader path
                logger.exception("VISCA link: error handling packet %s", raw.hex(" "))
        if self._reassembler.dropped_bytes != dropped_before:
            self._resyncs += 1
            logger.debug(
                "dropped %d garbage byte(s)", self._reassembler.dropped_bytes - dropped_before
            )

    def _on_packet(self, raw: bytes) -> None:
        try:
            packet = Packet.from_bytes(raw)
        except CodecError as exc:
            self._bad_packets += 1
            logger.debug("bad packet %s: %s", raw.hex(" "), exc)
            return
        if packet.receiver not in (CONTROLLER_ADDRESS, BROADCAST_ADDRESS) or (
            packet.receiver == CONTROLLER_ADDRESS and packet.sender == CONTROLLER_ADDRESS
        ):
            # A request seen on the line (echo on loop:// or a second controller), not a reply.
            self._stray += 1
            logger.debug("ignored non-reply packet %s", raw.hex(" "))
            return
        try:
            reply = decode_reply(packet)
        except CodecError as exc:
            self._bad_packets += 1
            logger.debug("unrecognised reply %s: %s", raw.hex(" "), exc)
            return
        self._packets_in += 1
        self._replies[type(reply).__name__] += 1
        self._last_reply = time.monotonic()
        logger.debug("received from %d: %r", packet.sender, reply)
        if isinstance(reply, AddressSetReply | BroadcastEcho):
            self._on_broadcast_reply(reply)
            return
        if isinstance(reply, NetworkChange):
            self._on_network_change(packet.sender)
            return
        cam = self._camera_for_reply(packet.sender)
        if cam is None:
            self._stray += 1
            logger.debug("reply from unknown camera %d dropped: %r", packet.sender, reply)
            return
        if isinstance(reply, Ack):
            self._on_ack(cam, reply.socket)
        elif isinstance(reply, Completion):
            self._on_completion(cam, reply.socket)
        elif isinstance(reply, ErrorReply):
            self._on_error(cam, reply.socket, reply.code)
        elif isinstance(reply, InquiryReply):
            self._on_inquiry_reply(cam, reply.data)

    def _camera_for_reply(self, sender: int) -> _CameraState | None:
        cam = self._cameras.get(sender)
        if cam is not None:
            return cam
        # Firmware quirk (DESIGN §5): some cameras answer from A0 (address 2) instead of 90.
        # With a single camera on the link there is no ambiguity: route the reply to it.
        if len(self._cameras) == 1:
            only = next(iter(self._cameras.values()))
            if not self._aliased_warned:
                self._aliased_warned = True
                logger.warning(
                    "camera %d replies with header %02X (as address %d); accepting it as the "
                    "only camera on %s",
                    only.address,
                    (sender + 8) << 4,
                    sender,
                    self.url,
                )
            return only
        return None

    def _on_ack(self, cam: _CameraState, socket: int) -> None:
        entry = cam.awaiting_ack
        if entry is None:
            self._stray += 1
            logger.debug("camera %d: stray ACK for socket %d", cam.address, socket)
            return
        previous = cam.sockets.get(socket)
        if previous is not None:
            # The camera only reuses a socket once its command ended, so that command's
            # Completion was lost on the line: it is over.
            self._lost_completions += 1
            logger.debug(
                "camera %d: socket %d reused; Completion of %s was lost",
                cam.address,
                socket,
                previous.name,
            )
            self._finish_command(cam, previous, None)
        self._first_reply_done(cam, entry)
        cam.awaiting_ack = None
        self._cancel_timer(entry)
        entry.socket = socket
        cam.sockets[socket] = entry
        _resolve(entry.acked, socket)
        entry.timer = self._call_later(
            entry.completion_timeout, self._on_completion_timeout, cam, entry
        )
        self._pump(cam)

    def _on_completion(self, cam: _CameraState, socket: int) -> None:
        entry = cam.sockets.get(socket)
        if entry is None:
            # Late (its command timed out) or duplicated: never give it to another command.
            self._stray += 1
            logger.debug("camera %d: stray Completion for idle socket %d", cam.address, socket)
            return
        self._finish_command(cam, entry, None)

    def _on_error(self, cam: _CameraState, socket: int, code: int) -> None:
        self._errors[code] += 1
        if code in (ErrorCode.CANCELLED, ErrorCode.NO_SOCKET):
            handled = False
            pending = cam.cancels.pop(socket, None)
            if pending is not None:
                self._cancel_timer(pending)
                _resolve(pending.result, code == ErrorCode.CANCELLED)
                handled = True
            running = cam.sockets.get(socket)
            if code == ErrorCode.CANCELLED and running is not None:
                self._finish_command(
                    cam, running, error_from_reply(code, socket, cam.address, running.name)
                )
                handled = True
            if not handled:
                self._stray += 1
                logger.debug("camera %d: stray cancel reply %02X/%d", cam.address, code, socket)
            return
        target: _Entry | None
        if (
            code in (ErrorCode.SYNTAX, ErrorCode.MESSAGE_LENGTH, ErrorCode.BUFFER_FULL)
            or not socket
        ):
            # Errors about the message itself answer the oldest request still owed a first reply.
            target = cam.first_reply[0] if cam.first_reply else None
        else:
            # Socket errors (not executable, …): the command awaiting its ACK is owed its first
            # reply now; otherwise the command running in that socket failed.
            target = cam.awaiting_ack or cam.sockets.get(socket)
        if target is None:
            self._stray += 1
            logger.debug("camera %d: stray error %02X in socket %d", cam.address, code, socket)
            return
        if isinstance(target, _InquiryEntry):
            self._finish_inquiry(
                cam, target, error_from_reply(code, socket, cam.address, target.name)
            )
            return
        assert isinstance(target, _CommandEntry)
        if target is cam.awaiting_ack:
            self._first_reply_done(cam, target)
            cam.awaiting_ack = None
            self._cancel_timer(target)
            if code == ErrorCode.BUFFER_FULL and self._retry_buffer_full(cam, target):
                return
        self._finish_command(cam, target, error_from_reply(code, socket, cam.address, target.name))

    def _retry_buffer_full(self, cam: _CameraState, entry: _CommandEntry) -> bool:
        if entry.retries >= self.timeouts.buffer_full_retries:
            return False
        entry.retries += 1
        self._buffer_full_retries += 1
        if len(cam.sockets) < cam.max_sockets:
            # The camera has more commands than the link knows of (a lost ACK left one
            # running): cancel the sockets the link believes idle so both are known free.
            self._resyncs += 1
            logger.debug("camera %d: buffer full with free sockets; cancelling them", cam.address)
            for socket in range(1, SOCKETS_PER_CAMERA + 1):
                if socket not in cam.sockets and socket not in cam.cancels:
                    internal = self._send_cancel(cam, socket)
                    internal.result.add_done_callback(_consume)
        cam.queue.appendleft(entry)
        entry.timer = self._call_later(self.timeouts.queue_s, self._on_queue_timeout, cam, entry)
        if cam.hold is not None:
            cam.hold.cancel()
        cam.hold = self._call_later(self.timeouts.buffer_full_backoff_s, self._release_hold, cam)
        logger.debug(
            "camera %d: buffer full; retry %d of %s", cam.address, entry.retries, entry.name
        )
        return True

    def _release_hold(self, cam: _CameraState) -> None:
        cam.hold = None
        self._pump(cam)

    def _on_inquiry_reply(self, cam: _CameraState, data: bytes) -> None:
        entry = cam.inquiry_pending
        if entry is None:
            self._stray += 1
            logger.debug("camera %d: stray inquiry reply %s", cam.address, data.hex(" "))
            return
        try:
            answer = entry.request.parse_reply(data)
        except CodecError as exc:
            # Not an answer to this inquiry: a straggler for an earlier one. Keep waiting.
            self._stray += 1
            logger.debug(
                "camera %d: reply %s does not fit %s: %s",
                cam.address,
                data.hex(" "),
                entry.name,
                exc,
            )
            return
        self._finish_inquiry(cam, entry, None, answer)

    def _on_broadcast_reply(self, reply: AddressSetReply | BroadcastEcho) -> None:
        for entry in self._broadcasts:
            if isinstance(reply, AddressSetReply) and isinstance(entry.request, AddressSet):
                match = True
            else:
                match = (
                    isinstance(reply, BroadcastEcho) and reply.message == entry.request.to_message()
                )
            if match and not entry.result.done():
                self._cancel_timer(entry)
                _resolve(entry.result, reply)
                return
        self._stray += 1
        logger.debug("stray broadcast reply %r", reply)

    def _on_network_change(self, sender: int) -> None:
        self._network_changes += 1
        # Before the chain was first addressed this is just a camera powering up as we connect.
        logger.log(
            logging.WARNING if self._addressed else logging.INFO,
            "camera %d on %s reported a Network Change (power cycle or re-cabling): "
            "re-addressing the chain",
            sender,
            self.url,
        )
        self._addressed = False
        self._fail_everything(
            ViscaNetworkChangeError(
                f"camera {sender} on {self.url} reported a Network Change while the request was "
                "pending; the camera is being re-initialised, issue the request again"
            )
        )
        self._schedule_reinit()

    # ---- internals: completing ------------------------------------------------------------

    def _finish_command(
        self, cam: _CameraState, entry: _CommandEntry, error: BaseException | None
    ) -> None:
        self._cancel_timer(entry)
        if entry.socket is not None and cam.sockets.get(entry.socket) is entry:
            del cam.sockets[entry.socket]
        if cam.awaiting_ack is entry:
            cam.awaiting_ack = None
        self._first_reply_done(cam, entry)
        if error is None:
            _resolve(entry.done, None)
            logger.debug("camera %d: %s completed", cam.address, entry.name)
        else:
            _fail(entry.acked, error)
            _fail(entry.done, error)
            logger.debug("camera %d: %s failed: %s", cam.address, entry.name, error)
        if cam.hold is not None and error is None:
            # A socket just freed: a command held back by buffer-full may go now.
            cam.hold.cancel()
            cam.hold = None
        self._pump(cam)

    def _finish_inquiry(
        self,
        cam: _CameraState,
        entry: _InquiryEntry,
        error: BaseException | None,
        answer: Any = None,
    ) -> None:
        self._cancel_timer(entry)
        if cam.inquiry_pending is entry:
            cam.inquiry_pending = None
        self._first_reply_done(cam, entry)
        if error is None:
            _resolve(entry.result, answer)
        else:
            _fail(entry.result, error)
        self._pump(cam)

    @staticmethod
    def _first_reply_done(cam: _CameraState, entry: _CommandEntry | _InquiryEntry) -> None:
        with contextlib.suppress(ValueError):
            cam.first_reply.remove(entry)

    # ---- internals: timeouts ----------------------------------------------------------------

    def _on_queue_timeout(self, cam: _CameraState, entry: _CommandEntry) -> None:
        entry.timer = None
        if entry in cam.queue:
            cam.queue.remove(entry)
            self._timeouts["queue"] += 1
            _fail(
                entry.acked,
                ViscaTimeoutError("free socket", self.timeouts.queue_s, entry.name, cam.address),
            )
            _fail(
                entry.done,
                ViscaTimeoutError("free socket", self.timeouts.queue_s, entry.name, cam.address),
            )

    def _on_inquiry_queue_timeout(self, cam: _CameraState, entry: _InquiryEntry) -> None:
        entry.timer = None
        if entry in cam.inquiries:
            cam.inquiries.remove(entry)
            self._timeouts["queue"] += 1
            _fail(
                entry.result,
                ViscaTimeoutError("turn to send", self.timeouts.queue_s, entry.name, cam.address),
            )

    def _on_ack_timeout(self, cam: _CameraState, entry: _CommandEntry) -> None:
        entry.timer = None
        if cam.awaiting_ack is not entry:
            return
        self._timeouts["ACK"] += 1
        cam.command_guard_until = time.monotonic() + self.timeouts.late_reply_guard_s
        self._finish_command(
            cam, entry, ViscaTimeoutError("ACK", self.timeouts.ack_s, entry.name, cam.address)
        )

    def _on_completion_timeout(self, cam: _CameraState, entry: _CommandEntry) -> None:
        entry.timer = None
        socket = entry.socket
        if socket is None or cam.sockets.get(socket) is not entry:
            return
        self._timeouts["Completion"] += 1
        # The command may still run (or its Completion was lost): cancel the socket so the
        # camera and the link agree it is free. The Cancel is written before any new command.
        if socket not in cam.cancels and self._connected:
            internal = self._send_cancel(cam, socket)
            internal.result.add_done_callback(_consume)
        self._finish_command(
            cam,
            entry,
            ViscaTimeoutError("Completion", entry.completion_timeout, entry.name, cam.address),
        )

    def _on_inquiry_timeout(self, cam: _CameraState, entry: _InquiryEntry) -> None:
        entry.timer = None
        if cam.inquiry_pending is not entry:
            return
        self._timeouts["inquiry reply"] += 1
        cam.inquiry_guard_until = time.monotonic() + self.timeouts.late_reply_guard_s
        self._finish_inquiry(
            cam,
            entry,
            ViscaTimeoutError("inquiry reply", self.timeouts.inquiry_s, entry.name, cam.address),
        )

    def _on_cancel_timeout(self, cam: _CameraState, entry: _CancelEntry) -> None:
        entry.timer = None
        if cam.cancels.get(entry.socket) is entry:
            del cam.cancels[entry.socket]
        self._timeouts["cancel reply"] += 1
        _fail(
            entry.result,
            ViscaTimeoutError("cancel reply", self.timeouts.cancel_s, entry.name, cam.address),
        )

    def _on_broadcast_timeout(self, entry: _BroadcastEntry) -> None:
        entry.timer = None
        self._timeouts["broadcast reply"] += 1
        _fail(
            entry.result,
            ViscaTimeoutError(f"{type(entry.request).__name__} reply", self.timeouts.broadcast_s),
        )

    # ---- internals: port up/down ------------------------------------------------------------

    async def _open_port(self) -> None:
        port = await asyncio.to_thread(self._port_factory, self.url, self.baudrate)
        try:
            port.reset_input_buffer()  # stale bytes from before we opened are not replies
        except (serial.SerialException, OSError):
            port.close()
            raise
        self._reassembler.clear()
        self._generation += 1
        self._port = port
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(
            target=self._reader_main,
            args=(port, self._generation, self._reader_stop, asyncio.get_running_loop()),
            name=f"visca-reader {self.url}",
            daemon=True,
        )
        self._connected = True
        self._reader.start()
        logger.info("VISCA port %s open at %d baud", self.url, self.baudrate)

    async def _close_port(self) -> None:
        port, reader = self._port, self._reader
        self._port = None
        self._reader = None
        self._generation += 1
        self._reader_stop.set()
        if port is not None:
            cancel_read = getattr(port, "cancel_read", None)
            if cancel_read is not None:
                with contextlib.suppress(Exception):
                    cancel_read()
        if reader is not None and reader is not threading.current_thread():
            await asyncio.to_thread(reader.join, READ_POLL_S * 10)
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()

    def _reader_main(
        self,
        port: SerialPortLike,
        generation: int,
        stop: threading.Event,
        loop: asyncio.AbstractEventLoop,
    ) -> None:
        while not stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting > 0 else 1)
            except Exception as exc:  # noqa: BLE001 - any failure of the port means it is gone
                if not stop.is_set():
                    with contextlib.suppress(RuntimeError):  # loop already closed
                        loop.call_soon_threadsafe(self._on_port_failure, generation, exc)
                return
            if data and not stop.is_set():
                try:
                    loop.call_soon_threadsafe(self._on_bytes, generation, data)
                except RuntimeError:
                    return

    def _on_port_failure(self, generation: int, exc: BaseException) -> None:
        if generation != self._generation or self._closing or not self._connected:
            return
        self._connected = False
        self._port_failures += 1
        self._addressed = False
        level = logging.DEBUG if self._down_reported else logging.WARNING
        self._down_reported = True
        logger.log(
            level,
            "VISCA port %s failed (%s): is the USB-serial adapter unplugged? reconnecting with "
            "backoff up to %.0f s",
            self.url,
            exc,
            self.timeouts.reconnect_max_s,
        )
        self._fail_everything(LinkDownError(self._down_message()))
        self._spawn(self._reconnect(), "reconnect")

    async def _reconnect(self) -> None:
        await self._close_port()
        delay = self.timeouts.reconnect_initial_s
        attempts = 0
        while not self._closing:
            await asyncio.sleep(delay)  # backoff pacing between attempts
            attempts += 1
            try:
                await self._open_port()
            except (serial.SerialException, OSError, ValueError) as exc:
                logger.debug("reopening %s failed (attempt %d): %s", self.url, attempts, exc)
                delay = min(delay * 2.0, self.timeouts.reconnect_max_s)
                continue
            self._reconnects += 1
            logger.info("VISCA port %s is back after %d attempt(s)", self.url, attempts)
            self._schedule_reinit()
            return

    def _schedule_reinit(self) -> None:
        self._reinit_requests += 1
        self._gated = True
        if self._reinit_task is not None and not self._reinit_task.done():
            return
        self._reinit_task = self._spawn(self._reinitialize(), "reinitialize")

    async def _reinitialize(self) -> None:
        _REINIT_CONTEXT.set(True)  # this task's context only
        try:
            while True:
                requested = self._reinit_requests
                try:
                    await self.ensure_addressed(force=True)
                except ViscaError as exc:
                    logger.warning("re-addressing the VISCA chain on %s failed: %s", self.url, exc)
                if self._reinit_requests != requested:
                    continue
                for callback in list(self._reinit_callbacks):
                    try:
                        async with asyncio.timeout(self.timeouts.reinit_s):
                            await callback()
                    except (ViscaError, TimeoutError) as exc:
                        logger.warning("re-initialising a camera on %s failed: %s", self.url, exc)
                    except Exception:  # a callback's bug must not stop the link
                        logger.exception("re-initialisation callback failed on %s", self.url)
                    if self._reinit_requests != requested:
                        break
                if self._reinit_requests == requested:
                    self._down_reported = False
                    return
        finally:
            self._gated = False
            for cam in list(self._cameras.values()):
                self._pump(cam)

    def _fail_everything(self, error: ViscaError) -> None:
        """Fail every waiter (port lost, closed, or chain reset) and forget the socket state."""
        for cam in self._cameras.values():
            entries: list[_Entry] = [*cam.queue, *cam.inquiries, *cam.sockets.values()]
            if cam.awaiting_ack is not None:
                entries.append(cam.awaiting_ack)
            if cam.inquiry_pending is not None:
                entries.append(cam.inquiry_pending)
            entries.extend(cam.cancels.values())
            cam.reset()
            for entry in entries:
                self._cancel_timer(entry)
                if isinstance(entry, _CommandEntry):
                    _fail(entry.acked, error)
                    _fail(entry.done, error)
                else:
                    _fail(entry.result, error)
        for broadcast in list(self._broadcasts):
            self._cancel_timer(broadcast)
            _fail(broadcast.result, error)

    # ---- internals: helpers -----------------------------------------------------------------

    def _require_up(self) -> None:
        if not self._connected or self._closing:
            raise LinkDownError(self._down_message())

    def _down_message(self) -> str:
        if self._closing:
            return f"VISCA link {self.url!r} is closed"
        return (
            f"VISCA port {self.url!r} is not open (adapter unplugged or camera port closed); "
            "the link is reconnecting, retry when it is back"
        )

    def _camera(self, address: int) -> _CameraState:
        check_range("camera address", address, MIN_CAMERA_ADDRESS, MAX_CAMERA_ADDRESS)
        cam = self._cameras.get(address)
        if cam is None:
            cam = self._cameras[address] = _CameraState(address)
        return cam

    def _future(self) -> asyncio.Future[Any]:
        return asyncio.get_running_loop().create_future()

    def _call_later(
        self, delay: float, callback: Callable[..., None], *args: Any
    ) -> asyncio.TimerHandle:
        return asyncio.get_running_loop().call_later(delay, callback, *args)

    @staticmethod
    def _cancel_timer(entry: _Entry | _BroadcastEntry) -> None:
        if entry.timer is not None:
            entry.timer.cancel()
            entry.timer = None

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        task = asyncio.get_running_loop().create_task(coro, name=f"visca {name} {self.url}")
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            logger.error("VISCA link task %s failed", task.get_name(), exc_info=task.exception())


def is_stop(command: Command) -> bool:
    """True for Pan-tiltDrive Stop and Focus Stop (they jump the queue)."""
    if isinstance(command, PanTiltDrive):
        return command.pan is PanDirection.STOP and command.tilt is TiltDirection.STOP
    return isinstance(command, FocusDrive) and command.direction is FocusDirection.STOP


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _CommandEntry:
    address: int
    request: Command
    completion_timeout: float
    acked: asyncio.Future[int]
    done: asyncio.Future[None]
    privileged: bool = False  # sent by the re-initialisation (passes the gate)
    socket: int | None = None
    retries: int = 0
    timer: asyncio.TimerHandle | None = None

    def __post_init__(self) -> None:
        self.acked.add_done_callback(_consume)
        self.done.add_done_callback(_consume)

    @property
    def name(self) -> str:
        return type(self.request).__name__


@dataclass(eq=False)
class _InquiryEntry:
    address: int
    request: Inquiry
    result: asyncio.Future[Any]
    privileged: bool = False
    timer: asyncio.TimerHandle | None = None

    def __post_init__(self) -> None:
        self.result.add_done_callback(_consume)

    @property
    def name(self) -> str:
        return type(self.request).__name__


@dataclass(eq=False)
class _CancelEntry:
    address: int
    socket: int
    result: asyncio.Future[bool]
    timer: asyncio.TimerHandle | None = None

    def __post_init__(self) -> None:
        self.result.add_done_callback(_consume)

    @property
    def name(self) -> str:
        return f"Cancel(socket {self.socket})"


@dataclass(eq=False)
class _BroadcastEntry:
    request: Broadcast
    result: asyncio.Future[Reply]
    timer: asyncio.TimerHandle | None = None

    def __post_init__(self) -> None:
        self.result.add_done_callback(_consume)


_Entry = _CommandEntry | _InquiryEntry | _CancelEntry
EntryT = TypeVar("EntryT", _CommandEntry, _InquiryEntry)


@dataclass(eq=False)
class _CameraState:
    address: int
    max_sockets: int = SOCKETS_PER_CAMERA
    queue: deque[_CommandEntry] = field(default_factory=deque)
    awaiting_ack: _CommandEntry | None = None
    sockets: dict[int, _CommandEntry] = field(default_factory=dict)
    inquiries: deque[_InquiryEntry] = field(default_factory=deque)
    inquiry_pending: _InquiryEntry | None = None
    first_reply: deque[_CommandEntry | _InquiryEntry] = field(default_factory=deque)
    cancels: dict[int, _CancelEntry] = field(default_factory=dict)
    hold: asyncio.TimerHandle | None = None
    pump_timer: asyncio.TimerHandle | None = None
    command_guard_until: float = 0.0
    inquiry_guard_until: float = 0.0

    def reset(self) -> None:
        self.queue.clear()
        self.awaiting_ack = None
        self.sockets.clear()
        self.inquiries.clear()
        self.inquiry_pending = None
        self.first_reply.clear()
        self.cancels.clear()
        for timer in (self.hold, self.pump_timer):
            if timer is not None:
                timer.cancel()
        self.hold = None
        self.pump_timer = None


def _consume(fut: asyncio.Future[Any]) -> None:
    """Mark a future's exception retrieved: the link owns these futures, callers may not wait."""
    if not fut.cancelled():
        fut.exception()


def _resolve(fut: asyncio.Future[Any], value: Any) -> None:
    if not fut.done():
        fut.set_result(value)


def _fail(fut: asyncio.Future[Any], error: BaseException) -> None:
    if not fut.done():
        fut.set_exception(error)


def _default_completion_s(request: Command) -> float:
    if isinstance(request, FocusDirect):
        return FOCUS_DIRECT_COMPLETION_TIMEOUT_S
    if isinstance(request, ZoomDirect):
        return ZOOM_DIRECT_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltAbsolute | PanTiltRelative):
        return PAN_TILT_MOVE_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltHome):
        return HOME_COMPLETION_TIMEOUT_S
    if isinstance(request, PanTiltReset):
        return RESET_COMPLETION_TIMEOUT_S
    if isinstance(request, CamPower):
        return POWER_COMPLETION_TIMEOUT_S
    if isinstance(request, FocusOnePush):
        return ONE_PUSH_AF_COMPLETION_TIMEOUT_S
    return DRIVE_COMPLETION_TIMEOUT_S  # PanTiltDrive, FocusDrive, FocusMode
