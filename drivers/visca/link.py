"""Asyncio VISCA link: a thin shell around :class:`drivers.visca.session.ViscaSession`.

All reply matching, queueing and timeouts live in the sans-IO session (its module doc lists the
rules). The link adds what needs I/O and a clock:

* a transport (:mod:`drivers.visca.transport`; a pyserial port by default), opened per
  connection through a factory, with reconnect and capped exponential backoff when it breaks;
* a future per ticket, resolved from the session's events; the waiter is registered before
  anything is written;
* ONE timer, armed at the session's next deadline;
* re-initialisation after a Network Change or a reconnect: Address Set + IF_Clear, then every
  *re-initialisation step* (:meth:`ViscaLink.add_reinit_step`) with a
  :class:`~drivers.visca.link_api.ReinitLink` — the explicit pass through the session's closed
  gate — then the plain callbacks (:meth:`ViscaLink.add_reinit_callback`) once the gate is open
  again.

What callers hold of a link (:class:`~drivers.visca.link_api.LinkApi`, the
:class:`~drivers.visca.link_api.CommandHandle` of a command, the ``ReinitLink``, the
:class:`~drivers.visca.link_api.LinkHealth` snapshot) was split into :mod:`drivers.visca.link_api`,
and the choice of transport by URL into :mod:`drivers.visca.transport`. What is left is the one
class :class:`ViscaLink` (~525 lines) and its private helpers, a little past ~600 lines: its
transport, timer, waiters, reconnect and re-initialisation share the transport generation, the
session's gate and the table of waiters, and are one object.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Coroutine
from dataclasses import dataclass, fields
from typing import Any, cast

from drivers.visca.codec_framing import check_range
from drivers.visca.codec_replies import AddressSetReply, Reply
from drivers.visca.codec_requests import (
    AddressSet,
    Broadcast,
    Cancel,
    Command,
    IFClear,
    IFClearBroadcast,
)
from drivers.visca.errors import (
    LinkDownError,
    ViscaError,
    ViscaTimeoutError,
)
from drivers.visca.ip import IpStats
from drivers.visca.link_api import (
    AnswerT,
    CommandHandle,
    InquiryLike,
    LinkHealth,
    ReinitCallback,
    ReinitLink,
    ReinitStep,
)
from drivers.visca.session import ViscaSession
from drivers.visca.session_types import (
    SOCKETS_PER_CAMERA,
    Acked,
    Answered,
    Completed,
    Failed,
    LinkTimeouts,
    NetworkChanged,
    SessionEvent,
)
from drivers.visca.transport import (
    PortFactory,
    Transport,
    TransportFactory,
    factory_for_url,
    open_failure_message,
    open_serial_port,
)

logger = logging.getLogger(__name__)

TRACE = 5  # raw bytes on the wire; below DEBUG (parsed packets)
logging.addLevelName(TRACE, "TRACE")


class ViscaLink:
    """The controller side of one VISCA line (one or more cameras on a daisy chain)."""

    def __init__(
        self,
        url: str,
        baudrate: int = 9600,
        *,
        timeouts: LinkTimeouts | None = None,
        port_factory: PortFactory = open_serial_port,
        transport_factory: TransportFactory | None = None,
    ) -> None:
        self.url = url
        self.baudrate = baudrate
        self.timeouts = timeouts or LinkTimeouts()
        self._transport_factory = transport_factory or factory_for_url(url, baudrate, port_factory)
        self._transport: Transport | None = None
        self._ip_totals: IpStats | None = None  # IP counters of closed connections
        self._generation = 0  # bumps on every (re)open: callbacks of an old transport are void
        self._session = ViscaSession(self.timeouts, name=url)
        self._session.connection_lost(time.monotonic(), LinkDownError(f"{url} not open yet"))
        self._waiters: dict[int, _Waiter] = {}
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self._address_lock = asyncio.Lock()
        self._addressed = False
        self._closing = False
        self._connected = False
        self._down_reported = False
        self._reinit_steps: list[ReinitStep] = []
        self._reinit_callbacks: list[ReinitCallback] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._reinit_task: asyncio.Task[None] | None = None
        self._reinit_requests = 0  # bumped per reason to re-initialise; a running pass restarts
        self.chain_length: int | None = None
        self._reconnects = 0
        self._port_failures = 0

    # ---- lifecycle --------------------------------------------------------------------------

    async def open(self) -> None:
        """Open the transport (stale input flushed); raise LinkDownError if it cannot be opened."""
        self._closing = False
        try:
            await self._connect()
        except (OSError, ValueError) as exc:
            raise LinkDownError(open_failure_message(self.url, self.baudrate, exc)) from exc

    async def close(self) -> None:
        """Stop background tasks, fail every waiter with LinkDownError, close the transport."""
        self._closing = True
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._dispatch(
            self._session.connection_lost(
                time.monotonic(), LinkDownError(f"VISCA link {self.url!r} was closed")
            )
        )
        self._cancel_timer()
        await self._close_transport()
        self._connected = False

    async def __aenter__(self) -> ViscaLink:
        await self.open()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        """True while the transport is open."""
        return self._connected

    @property
    def session(self) -> ViscaSession:
        """The sans-IO session inside (read-only use: counters, state)."""
        return self._session

    def add_reinit_step(self, step: ReinitStep) -> None:
        """Run ``step(reinit_link)`` behind the closed gate after every re-addressing.

        ``reinit_link``'s requests pass the gate that holds everyone else's until every step
        ran (a user's retried Focus Direct must not reach a camera still in autofocus, nor be
        wiped by the re-initialisation's IF_Clear).
        """
        if step not in self._reinit_steps:
            self._reinit_steps.append(step)

    def remove_reinit_step(self, step: ReinitStep) -> None:
        """Forget a step added with :meth:`add_reinit_step`."""
        with contextlib.suppress(ValueError):
            self._reinit_steps.remove(step)

    def add_reinit_callback(self, callback: ReinitCallback) -> None:
        """Run ``callback`` after the chain was re-addressed and re-initialised (gate open)."""
        if callback not in self._reinit_callbacks:
            self._reinit_callbacks.append(callback)

    def remove_reinit_callback(self, callback: ReinitCallback) -> None:
        """Forget a callback added with :meth:`add_reinit_callback`."""
        with contextlib.suppress(ValueError):
            self._reinit_callbacks.remove(callback)

    def set_max_sockets(self, address: int, sockets: int) -> None:
        """Limit commands in flight for ``address`` (VersionInq's KK; 1 or 2)."""
        self._session.set_max_sockets(address, sockets)

    def health(self) -> LinkHealth:
        """Counters and state for status reporting."""
        s = self._session.stats()
        return LinkHealth(
            url=self.url,
            connected=self._connected,
            bytes_in=s.bytes_in,
            bytes_out=s.bytes_out,
            packets_in=s.packets_in,
            packets_out=s.packets_out,
            replies=s.replies,
            errors_by_code=s.errors_by_code,
            timeouts=s.timeouts,
            dropped_bytes=s.dropped_bytes,
            bad_packets=s.bad_packets,
            stray_replies=s.stray_replies,
            lost_completions=s.lost_completions,
            resyncs=s.resyncs,
            buffer_full_retries=s.buffer_full_retries,
            network_changes=s.network_changes,
            reconnects=self._reconnects,
            port_failures=self._port_failures,
            last_reply_monotonic=s.last_reply_t,
            chain_length=self.chain_length,
            ip=self._ip_stats(),
        )

    def _ip_stats(self) -> IpStats | None:
        """The VISCA-over-IP counters over every connection so far (None: never over IP)."""
        channel = getattr(self._transport, "channel", None)
        if channel is None:
            return self._ip_totals
        return _add_ip_stats(self._ip_totals or IpStats(), channel.stats)

    def running(self, address: int) -> dict[int, Command]:
        """Commands in flight for ``address`` by socket (as the session believes)."""
        return self._session.running(address)

    def completion_inferred(self, handle: CommandHandle) -> bool:
        """The caller saw the command's move end (by inquiry): complete it as if its Completion
        came; True if it was still running (its Completion counts as lost)."""
        socket = handle.socket
        ended = self._session.completion_lost(handle._waiter.ticket, time.monotonic())
        channel = getattr(self._transport, "channel", None)
        if ended and socket is not None and channel is not None:
            channel.socket_done(socket)  # VISCA over IP: a late Completion must not follow
        self._service()
        return ended

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
        return self._submit(address, command, priority, completion_timeout, privileged=False)

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
        return await self._inquire(address, inquiry, privileged=False)

    async def cancel(self, address: int, socket: int) -> bool:
        """Cancel the command in ``socket``; True if one was cancelled, False if it was idle."""
        self._require_up()
        check_range("socket", socket, 1, SOCKETS_PER_CAMERA)
        waiter = self._request(Cancel(socket), address=address)
        return cast(bool, await self._await(waiter, waiter.result))

    async def broadcast(self, request: Broadcast) -> Reply:
        """Send a broadcast (Address Set, IF_Clear) and return the packet that came back."""
        self._require_up()
        waiter = self._request(request)
        return cast(Reply, await self._await(waiter, waiter.result))

    async def ensure_addressed(self, *, force: bool = False) -> int:
        """Address Set + IF_Clear (broadcast) once per connection; return the chain length."""
        async with self._address_lock:
            if self._addressed and not force and self.chain_length is not None:
                return self.chain_length
            reply = await self.broadcast(AddressSet())
            if not isinstance(reply, AddressSetReply):  # pragma: no cover - matched by type
                raise ViscaError(f"Address Set answered by {reply!r}")
            self.chain_length = reply.next_address - 1
            try:
                await self.broadcast(IFClearBroadcast())
            except ViscaTimeoutError:
                # The spec echoes the broadcast IF_Clear; some devices and emulators clear but
                # stay silent. Each camera's own IF_Clear (answered z0 50 FF) does the same.
                logger.warning(
                    "the broadcast IF_Clear was not echoed on %s; clearing each of the %d "
                    "camera(s) with its own IF_Clear instead",
                    self.url, self.chain_length,
                )  # fmt: skip
                for address in range(1, self.chain_length + 1):
                    await self._inquire(address, IFClear(), privileged=True)
            self._addressed = True
            self._session.mark_addressed()
            logger.info("VISCA chain on %s addressed: %d camera(s)", self.url, self.chain_length)
            return self.chain_length

    # ---- internals: requests ------------------------------------------------------------------

    def _submit(
        self,
        address: int,
        command: Command,
        priority: bool | None,
        completion_timeout: float | None,
        *,
        privileged: bool,
    ) -> CommandHandle:
        if getattr(command, "KIND", None) != "command":
            raise TypeError(f"{type(command).__name__} is not a command (use inquire/broadcast)")
        self._require_up()
        waiter = self._request(
            command,
            address=address,
            priority=priority,
            completion_timeout=completion_timeout,
            privileged=privileged,
            acked=True,
        )
        return CommandHandle(self, waiter, command, address)

    async def _inquire(
        self, address: int, inquiry: InquiryLike[AnswerT], *, privileged: bool
    ) -> AnswerT:
        if getattr(inquiry, "KIND", None) != "inquiry":
            raise TypeError(f"{type(inquiry).__name__} is not an inquiry")
        self._require_up()
        waiter = self._request(inquiry, address=address, privileged=privileged)
        return cast(AnswerT, await self._await(waiter, waiter.result))

    def _request(
        self,
        request: Any,
        *,
        address: int = 1,
        priority: bool | None = None,
        completion_timeout: float | None = None,
        privileged: bool = False,
        acked: bool = False,
    ) -> _Waiter:
        """Hand ``request`` to the session, register its waiter, then write what is due."""
        loop = asyncio.get_running_loop()
        ticket = self._session.submit(
            request,
            time.monotonic(),
            address=address,
            priority=priority,
            completion_timeout=completion_timeout,
            privileged=privileged,
        )
        waiter = _Waiter(ticket, loop.create_future(), loop.create_future() if acked else None)
        self._waiters[ticket] = waiter
        self._service()
        return waiter

    async def _await(self, waiter: _Waiter, fut: asyncio.Future[Any]) -> Any:
        # The session ends every ticket; shield so a cancelled caller does not cancel the future
        # other awaits of the same handle still use.
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            if self._session.abandon(waiter.ticket):
                self._waiters.pop(waiter.ticket, None)
                waiter.cancel()
            raise

    # ---- internals: the session's clock and I/O -----------------------------------------------

    def _service(self, now: float | None = None) -> None:
        """Run the session's expired waits, dispatch its events, write, re-arm the timer."""
        if now is None:
            now = time.monotonic()
        self._dispatch(self._session.poll(now))
        self._flush()
        self._rearm()

    def _on_data(self, generation: int, data: bytes) -> None:
        if generation != self._generation or self._closing:
            return
        logger.log(TRACE, "%s << %s", self.url, data.hex(" "))
        self._dispatch(self._session.receive(data, time.monotonic()))
        self._flush()
        self._rearm()

    def _flush(self) -> None:
        transport = self._transport
        packets = self._session.packets_to_send()
        if transport is None or not self._connected:
            return
        for packet in packets:
            try:
                transport.write(packet)
            except OSError as exc:
                self._on_lost(self._generation, exc)
                return
            logger.log(TRACE, "%s >> %s", self.url, packet.hex(" "))

    def _rearm(self) -> None:
        deadline = None if self._closing else self._session.next_deadline()
        if deadline == self._timer_at and self._timer is not None:
            return
        self._cancel_timer()
        if deadline is None:
            return
        delay = max(0.0, deadline - time.monotonic())
        self._timer = asyncio.get_running_loop().call_later(delay, self._on_timer, deadline)
        self._timer_at = deadline

    def _on_timer(self, deadline: float) -> None:
        self._timer = None
        self._timer_at = None
        # The loop may fire a hair early (its clock resolution): the deadline has come.
        self._service(max(time.monotonic(), deadline))

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer = None
        self._timer_at = None

    def _dispatch(self, events: list[SessionEvent]) -> None:
        for event in events:
            if isinstance(event, NetworkChanged):
                self._addressed = False
                self._schedule_reinit()
                continue
            waiter = self._waiters.get(event.ticket)
            if waiter is None:
                continue  # the caller abandoned it
            if isinstance(event, Acked):
                waiter.socket = event.socket
                if waiter.acked is not None:
                    _resolve(waiter.acked, event.socket)
                continue
            del self._waiters[event.ticket]
            if isinstance(event, Completed):
                _resolve(waiter.result, None)
            elif isinstance(event, Answered):
                _resolve(waiter.result, event.value)
            elif isinstance(event, Failed):
                if waiter.acked is not None:
                    _fail(waiter.acked, event.error)
                _fail(waiter.result, event.error)

    # ---- internals: transport up/down -------------------------------------------------------

    async def _connect(self) -> None:
        generation = self._generation + 1
        transport = await self._transport_factory(
            lambda data: self._on_data(generation, data),
            lambda exc: self._on_lost(generation, exc),
        )
        self._generation = generation
        self._transport = transport
        self._connected = True
        self._session.connection_made(time.monotonic())
        self._service()
        logger.info("VISCA port %s open at %d baud", self.url, self.baudrate)

    async def _close_transport(self) -> None:
        transport = self._transport
        self._transport = None
        self._generation += 1
        if transport is not None:
            channel = getattr(transport, "channel", None)
            if channel is not None:
                self._ip_totals = _add_ip_stats(self._ip_totals or IpStats(), channel.stats)
            with contextlib.suppress(Exception):
                await transport.close()

    def _on_lost(self, generation: int, exc: BaseException) -> None:
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
        self._dispatch(
            self._session.connection_lost(time.monotonic(), LinkDownError(self._down_message()))
        )
        self._cancel_timer()
        self._spawn(self._reconnect(), "reconnect")

    async def _reconnect(self) -> None:
        await self._close_transport()
        delay = self.timeouts.reconnect_initial_s
        attempts = 0
        while not self._closing:
            await asyncio.sleep(delay)  # backoff pacing between attempts
            attempts += 1
            self._session.close_gate()  # nothing but the re-initialisation until it is done
            try:
                await self._connect()
            except (OSError, ValueError) as exc:
                logger.debug("reopening %s failed (attempt %d): %s", self.url, attempts, exc)
                delay = min(delay * 2.0, self.timeouts.reconnect_max_s)
                continue
            self._reconnects += 1
            logger.info("VISCA port %s is back after %d attempt(s)", self.url, attempts)
            self._schedule_reinit()
            return

    # ---- internals: re-initialisation -------------------------------------------------------

    def _schedule_reinit(self) -> None:
        self._reinit_requests += 1
        self._session.close_gate()
        if self._reinit_task is not None and not self._reinit_task.done():
            return
        self._reinit_task = self._spawn(self._reinitialize(), "reinitialize")

    async def _reinitialize(self) -> None:
        gate = ReinitLink(self)
        while True:
            requested = await self._reinit_pass(gate)
            for callback in list(self._reinit_callbacks):
                try:
                    async with asyncio.timeout(self.timeouts.reinit_s):
                        await callback()
                except (ViscaError, TimeoutError) as exc:
                    logger.warning("after re-initialising on %s: %s", self.url, exc)
                except Exception:  # a callback's bug must not stop the link
                    logger.exception("re-initialisation callback failed on %s", self.url)
            if self._reinit_requests == requested:
                return

    async def _reinit_pass(self, gate: ReinitLink) -> int:
        """Re-address and run the steps until no new reason came in; open the gate after."""
        try:
            while True:
                requested = self._reinit_requests
                try:
                    await self.ensure_addressed(force=True)
                except ViscaError as exc:
                    logger.warning("re-addressing the VISCA chain on %s failed: %s", self.url, exc)
                if self._reinit_requests != requested:
                    continue
                for step in list(self._reinit_steps):
                    try:
                        async with asyncio.timeout(self.timeouts.reinit_s):
                            await step(gate)
                    except (ViscaError, TimeoutError) as exc:
                        logger.warning("re-initialising a camera on %s failed: %s", self.url, exc)
                    except Exception:  # a step's bug must not stop the link
                        logger.exception("re-initialisation step failed on %s", self.url)
                    if self._reinit_requests != requested:
                        break
                if self._reinit_requests == requested:
                    self._down_reported = False
                    return requested
        finally:
            if not self._closing:
                self._session.open_gate(time.monotonic())
                self._service()

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

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        task = asyncio.get_running_loop().create_task(coro, name=f"visca {name} {self.url}")
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            logger.error("VISCA link task %s failed", task.get_name(), exc_info=task.exception())


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _Waiter:
    ticket: int
    result: asyncio.Future[Any]
    acked: asyncio.Future[int] | None = None
    socket: int | None = None

    def __post_init__(self) -> None:
        self.result.add_done_callback(_consume)
        if self.acked is not None:
            self.acked.add_done_callback(_consume)

    def cancel(self) -> None:
        self.result.cancel()
        if self.acked is not None:
            self.acked.cancel()


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


def _add_ip_stats(a: IpStats, b: IpStats) -> IpStats:
    """Field-wise sum of two channels' counters."""
    return IpStats(**{f.name: getattr(a, f.name) + getattr(b, f.name) for f in fields(IpStats)})
