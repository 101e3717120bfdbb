"""Per-camera bookkeeping of :class:`drivers.visca.session.ViscaSession` (private to it).

The queue entries of one request each (command, inquiry, Cancel, broadcast) and the state the
session keeps per camera address: queues, the command awaiting its ACK, the commands in the
sockets, the outstanding inquiry, pending Cancels, backoff and late-reply guards. Plain data: all
the logic that moves entries between these is in the session.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, TypeAlias, TypeVar

from drivers.visca.codec_requests import Broadcast, Command
from drivers.visca.session_types import SOCKETS_PER_CAMERA, InquiryLike


@dataclass(eq=False)
class _CommandEntry:
    ticket: int
    address: int
    request: Command
    completion_timeout: float
    privileged: bool = False  # sent by the re-initialisation (passes the gate)
    deadline: float = math.inf
    socket: int | None = None
    retries: int = 0

    @property
    def name(self) -> str:
        return type(self.request).__name__


@dataclass(eq=False)
class _InquiryEntry:
    ticket: int
    address: int
    request: InquiryLike
    privileged: bool = False
    deadline: float = math.inf

    @property
    def name(self) -> str:
        return type(self.request).__name__


@dataclass(eq=False)
class _CancelEntry:
    address: int
    socket: int
    deadline: float = math.inf
    tickets: list[int] = field(default_factory=list)  # callers waiting (none for internal ones)

    @property
    def name(self) -> str:
        return f"Cancel(socket {self.socket})"


@dataclass(eq=False)
class _BroadcastEntry:
    ticket: int
    request: Broadcast
    deadline: float = math.inf

    @property
    def name(self) -> str:
        return type(self.request).__name__


_Entry: TypeAlias = _CommandEntry | _InquiryEntry | _CancelEntry | _BroadcastEntry
_Waiting: TypeAlias = tuple[str, "_CameraState | None", _Entry]


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
    hold_until: float = -math.inf  # buffer-full backoff: no command before this
    command_guard_until: float = -math.inf
    inquiry_guard_until: float = -math.inf

    def reset(self) -> None:
        self.queue.clear()
        self.awaiting_ack = None
        self.sockets.clear()
        self.inquiries.clear()
        self.inquiry_pending = None
        self.first_reply.clear()
        self.cancels.clear()
        self.hold_until = -math.inf


EntryT = TypeVar("EntryT", _CommandEntry, _InquiryEntry)


def _discard(entries: deque[Any], entry: object) -> None:
    if entry in entries:
        entries.remove(entry)
