"""The VISCA link as its callers see it: the protocol the camera API needs, what a link hands out.

* :class:`LinkApi`: what :class:`drivers.visca.camera.Camera` needs of a link — the
  :class:`drivers.visca.link.ViscaLink` itself, or the :class:`ReinitLink` a re-initialisation
  step is given; :class:`InquiryLike`, :data:`ReinitStep` and :data:`ReinitCallback` type its
  arguments;
* :class:`CommandHandle`: a submitted command, whose ACK and Completion are awaited separately;
* :class:`ReinitLink`: the link seen from a re-initialisation step, whose requests pass the
  session's closed gate;
* :class:`LinkHealth`: the snapshot of the link's counters for status reporting.

Split from :mod:`drivers.visca.link`, which keeps :class:`~drivers.visca.link.ViscaLink` (the
asyncio shell: transport, timer, waiters, reconnect, re-initialisation); the handles call back
into it.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, TypeVar, cast

from drivers.visca.codec_replies import InquiryData
from drivers.visca.codec_requests import Command
from drivers.visca.ip import IpStats

if TYPE_CHECKING:
    from drivers.visca.link import ViscaLink, _Waiter

AnswerT_co = TypeVar("AnswerT_co", bound=InquiryData, covariant=True)
AnswerT = TypeVar("AnswerT", bound=InquiryData)


class InquiryLike(Protocol[AnswerT_co]):
    """An inquiry of the codec: ``to_message`` frames it, ``parse_reply`` types its answer."""

    def to_message(self) -> bytes: ...

    def parse_reply(self, data: bytes) -> AnswerT_co: ...


ReinitCallback = Callable[[], Awaitable[None]]


class LinkApi(Protocol):
    """What the camera API needs of a link (:class:`ViscaLink` or a :class:`ReinitLink`)."""

    @property
    def url(self) -> str: ...

    def submit(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> CommandHandle: ...

    async def command(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> None: ...

    async def inquire(self, address: int, inquiry: InquiryLike[AnswerT]) -> AnswerT: ...

    async def cancel(self, address: int, socket: int) -> bool: ...

    async def ensure_addressed(self, *, force: bool = False) -> int: ...

    def set_max_sockets(self, address: int, sockets: int) -> None: ...

    def running(self, address: int) -> dict[int, Command]: ...

    def completion_inferred(self, handle: CommandHandle) -> bool: ...

    def add_reinit_callback(self, callback: ReinitCallback) -> None: ...

    def add_reinit_step(self, step: ReinitStep) -> None: ...


ReinitStep = Callable[[LinkApi], Awaitable[None]]


class CommandHandle:
    """A command submitted to the link: await its ACK (socket) and its Completion separately."""

    def __init__(self, link: ViscaLink, waiter: _Waiter, request: Command, address: int) -> None:
        self._link = link
        self._waiter = waiter
        self._request = request
        self._address = address

    @property
    def request(self) -> Command:
        """The command."""
        return self._request

    @property
    def address(self) -> int:
        """The camera address."""
        return self._address

    @property
    def socket(self) -> int | None:
        """The socket the camera put the command in (None before its ACK)."""
        return self._waiter.socket

    def done(self) -> bool:
        """True once the command completed or failed."""
        return self._waiter.result.done()

    async def acked(self) -> int:
        """Wait for the ACK and return the socket; raise the command's error if it failed."""
        assert self._waiter.acked is not None
        return cast(int, await self._link._await(self._waiter, self._waiter.acked))

    async def completed(self) -> None:
        """Wait for the Completion; raise ViscaErrorReply/ViscaTimeoutError/LinkDownError."""
        await self._link._await(self._waiter, self._waiter.result)


class ReinitLink:
    """The link as a re-initialisation step sees it: its requests pass the closed gate."""

    def __init__(self, link: ViscaLink) -> None:
        self._link = link

    @property
    def url(self) -> str:
        """The link's URL."""
        return self._link.url

    def submit(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> CommandHandle:
        """:meth:`ViscaLink.submit`, through the gate."""
        return self._link._submit(address, command, priority, completion_timeout, privileged=True)

    async def command(
        self,
        address: int,
        command: Command,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> None:
        """:meth:`ViscaLink.command`, through the gate."""
        handle = self.submit(
            address, command, priority=priority, completion_timeout=completion_timeout
        )
        await handle.completed()

    async def inquire(self, address: int, inquiry: InquiryLike[AnswerT]) -> AnswerT:
        """:meth:`ViscaLink.inquire`, through the gate."""
        return await self._link._inquire(address, inquiry, privileged=True)

    async def cancel(self, address: int, socket: int) -> bool:
        """:meth:`ViscaLink.cancel` (Cancels are never held)."""
        return await self._link.cancel(address, socket)

    async def ensure_addressed(self, *, force: bool = False) -> int:
        """:meth:`ViscaLink.ensure_addressed` (broadcasts are never held)."""
        return await self._link.ensure_addressed(force=force)

    def set_max_sockets(self, address: int, sockets: int) -> None:
        """:meth:`ViscaLink.set_max_sockets`."""
        self._link.set_max_sockets(address, sockets)

    def running(self, address: int) -> dict[int, Command]:
        """:meth:`ViscaLink.running`."""
        return self._link.running(address)

    def completion_inferred(self, handle: CommandHandle) -> bool:
        """:meth:`ViscaLink.completion_inferred`."""
        return self._link.completion_inferred(handle)

    def add_reinit_callback(self, callback: ReinitCallback) -> None:
        """:meth:`ViscaLink.add_reinit_callback`."""
        self._link.add_reinit_callback(callback)

    def add_reinit_step(self, step: ReinitStep) -> None:
        """:meth:`ViscaLink.add_reinit_step`."""
        self._link.add_reinit_step(step)


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
    ip: IpStats | None = None  # VISCA over IP channel counters (None on serial and TCP)
