"""Sans-IO VISCA controller session: all reply matching, queueing and timeouts, fed bytes and time.

A :class:`ViscaSession` is the controller side of one VISCA line (one or more cameras on a daisy
chain) as a state machine. It never reads a clock, sleeps or touches a port: a shell (the asyncio
:class:`drivers.visca.link.ViscaLink`, or the virtual-time bus of the bench) calls

* :meth:`ViscaSession.submit` with a request and the current time, getting a ticket;
* :meth:`ViscaSession.receive` with the bytes read and the time they were read;
* :meth:`ViscaSession.poll` at (or after) :meth:`ViscaSession.next_deadline`;
* :meth:`ViscaSession.packets_to_send` to take the VISCA packets it must write, in order;

and gets :data:`SessionEvent` values back (ACK, Completion, answer, failure, Network Change).

For each camera address the session keeps

* a bounded command queue and at most two commands in flight (the camera's two sockets; one if
  its VersionInq says so). A command is written only when no earlier command to the same camera
  still waits for its ACK, so the ACK (or error) that comes back belongs to exactly one command,
  and from then on its Completion is matched by *socket*: a Completion for a socket the session
  no longer has a command in (late, after a timeout) is counted and dropped, never given to
  another command;
* inquiries, one outstanding at a time, matched in order (they are answered without ACK, even
  while both sockets are busy); a reply whose data does not parse for the outstanding inquiry is
  a straggler and is dropped;
* pending Cancels per socket (``z0 6p 04``: cancelled; ``z0 6p 05``: the socket was idle).

Stops (Pan-tiltDrive stop, Focus Stop) jump the queue and Cancels are written at once. An
unexpected buffer-full is recovered by waiting for a socket to free (bounded retries) and, if the
session believes a socket is free that the camera says is not, cancelling it (a resync). After an
ACK or inquiry timeout the next request of that kind is held for a short guard so a straggler
cannot be taken for its answer. A Network Change fails every waiter with
:class:`ViscaNetworkChangeError`, closes the *gate* (only requests submitted with
``privileged=True`` go out until :meth:`ViscaSession.open_gate`) and reports
:class:`NetworkChanged`: the shell re-addresses the chain and re-initialises the cameras.

Every wait is a deadline (:class:`LinkTimeouts`), so every ticket ends in exactly one final event.

The timings, request, event and counter types live in :mod:`drivers.visca.session_types` (import
them from there) and the per-camera bookkeeping in :mod:`drivers.visca.session_state`.

Why this module is past the ~600-line guideline: it is one state machine and nothing else. The
submit, send, reply and deadline paths of :class:`ViscaSession` all read and write the same state
(per camera: the command awaiting its ACK, the sockets, the order owed a first reply, the guards;
the table of live tickets; the event list) and keep its invariants together (an ACK belongs to
the one command written since the last; every ticket ends in exactly one final event). Spreading
its methods over modules (mixins, a chain of base classes) would scatter those invariants over
files; what is not the state machine, its vocabulary and its bookkeeping records, is already in
the two modules above.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from typing import Any, cast

from drivers.visca.codec import decode_reply, encode_request
from drivers.visca.codec_framing import (
    BROADCAST_ADDRESS,
    CONTROLLER_ADDRESS,
    MAX_CAMERA_ADDRESS,
    MIN_CAMERA_ADDRESS,
    CodecError,
    Packet,
    Reassembler,
    check_range,
)
from drivers.visca.codec_replies import (
    Ack,
    AddressSetReply,
    BroadcastEcho,
    Completion,
    ErrorCode,
    ErrorReply,
    InquiryData,
    InquiryReply,
    NetworkChange,
)
from drivers.visca.codec_requests import (
    BROADCAST_TYPES,
    COMMAND_TYPES,
    AddressSet,
    Broadcast,
    Cancel,
    Command,
)
from drivers.visca.errors import (
    LinkBusyError,
    ViscaError,
    ViscaNetworkChangeError,
    ViscaTimeoutError,
    error_from_reply,
)
from drivers.visca.session_state import (
    EntryT,
    _BroadcastEntry,
    _CameraState,
    _CancelEntry,
    _CommandEntry,
    _discard,
    _Entry,
    _InquiryEntry,
    _Waiting,
)
from drivers.visca.session_types import (
    BROADCAST_QUEUE_MAX,
    COMMAND_QUEUE_MAX,
    INQUIRY_QUEUE_MAX,
    SOCKETS_PER_CAMERA,
    Acked,
    Answered,
    Completed,
    Failed,
    InquiryLike,
    LinkTimeouts,
    NetworkChanged,
    SessionEvent,
    SessionRequest,
    SessionStats,
    is_stop,
)

logger = logging.getLogger(__name__)


class ViscaSession:
    """The controller side of one VISCA line as a pure state machine (see the module doc)."""

    def __init__(self, timeouts: LinkTimeouts | None = None, *, name: str = "VISCA line") -> None:
        self.timeouts = timeouts or LinkTimeouts()
        self.name = name  # for log and error messages (the link passes its URL)
        self._reassembler = Reassembler()
        self._cameras: dict[int, _CameraState] = {}
        self._broadcasts: deque[_BroadcastEntry] = deque()
        self._broadcast_pending: _BroadcastEntry | None = None
        self._live: dict[int, _Entry] = {}
        self._next_ticket = 1
        self._outgoing: list[bytes] = []
        self._events: list[SessionEvent] = []
        self._connected = True
        self._clock = -math.inf  # the latest time a caller passed in
        self._gated = False
        self._addressed = False  # a Network Change before the first addressing is a power-up
        self._aliased_warned = False
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
        self._last_reply: float | None = None

    # ---- requests ---------------------------------------------------------------------------

    def submit(
        self,
        request: SessionRequest,
        now: float,
        *,
        address: int = 1,
        priority: bool | None = None,
        completion_timeout: float | None = None,
        privileged: bool = False,
    ) -> int:
        """Queue ``request`` for camera ``address`` at ``now``; return its ticket.

        A command ends in Completed or Failed (after Acked on success); an inquiry, broadcast or
        Cancel in Answered or Failed. ``priority`` puts a command at the head of its queue
        (default: True for Stops). ``privileged`` requests pass the closed gate (the
        re-initialisation's own). Raises LinkBusyError when the camera's queue is full. Events
        this causes come with the next :meth:`receive` or :meth:`poll`.
        """
        self._expire(now)
        if isinstance(request, BROADCAST_TYPES):
            return self._submit_broadcast(request, now)
        cam = self._camera(address)
        if isinstance(request, COMMAND_TYPES):
            return self._submit_command(
                cam,
                request,
                now,
                priority=priority,
                completion_timeout=completion_timeout,
                privileged=privileged,
            )
        if isinstance(request, Cancel):
            return self._submit_cancel(cam, request.socket, now)
        if getattr(request, "KIND", None) == "inquiry":
            return self._submit_inquiry(cam, cast(InquiryLike, request), now, privileged)
        raise TypeError(f"{type(request).__name__} is not a VISCA request")

    def abandon(self, ticket: int) -> bool:
        """The caller no longer waits: drop a queued request; True if it was dropped.

        A request already written still takes its replies (and still ends in an event).
        """
        entry = self._live.get(ticket)
        if isinstance(entry, _CommandEntry | _InquiryEntry):
            cam = self._cameras[entry.address]
            queue: deque[Any] = cam.queue if isinstance(entry, _CommandEntry) else cam.inquiries
            if entry in queue:
                queue.remove(entry)
                del self._live[ticket]
                return True
        elif isinstance(entry, _BroadcastEntry) and entry in self._broadcasts:
            self._broadcasts.remove(entry)
            del self._live[ticket]
            return True
        return False

    def completion_lost(self, ticket: int, now: float) -> bool:
        """End a running command as completed: its caller saw the move end but no Completion came.

        True if the command was running in a socket (counted as a lost Completion); a
        Completion arriving later is then a stray reply for an idle socket.
        """
        entry = self._live.get(ticket)
        if not isinstance(entry, _CommandEntry) or entry.socket is None:
            return False
        cam = self._cameras[entry.address]
        if cam.sockets.get(entry.socket) is not entry:
            return False
        self._lost_completions += 1
        logger.debug(
            "camera %d: %s ended by inquiry; its Completion was lost", cam.address, entry.name
        )
        self._finish_command(cam, entry, None, now)
        return True

    # ---- input and time ---------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[SessionEvent]:
        """Bytes read from the line at ``now``; return the events they (and expired waits) cause."""
        self._expire(now)
        self._bytes_in += len(data)
        dropped_before = self._reassembler.dropped_bytes
        for raw in self._reassembler.feed(data):
            try:
                self._on_packet(raw, now)
            except Exception:  # a bug in matching must not kill the reader path
                logger.exception("%s: error handling packet %s", self.name, raw.hex(" "))
        if self._reassembler.dropped_bytes != dropped_before:
            self._resyncs += 1
            logger.debug(
                "dropped %d garbage byte(s)", self._reassembler.dropped_bytes - dropped_before
            )
        self._pump_all(now)
        return self._take_events()

    def poll(self, now: float) -> list[SessionEvent]:
        """Handle every wait that expired by ``now``; return the events since the last call."""
        self._expire(now)
        self._pump_all(now)
        return self._take_events()

    def next_deadline(self) -> float | None:
        """The earliest time at which :meth:`poll` has something to do, or None."""
        best = min(self._times(), default=math.inf)
        return None if best == math.inf else max(best, self._clock)

    def packets_to_send(self) -> list[bytes]:
        """Take the VISCA packets to write, in order (each a complete ``8x … FF`` packet)."""
        out, self._outgoing = self._outgoing, []
        return out

    def data_to_send(self) -> bytes:
        """Take the bytes to write on a byte stream (the packets concatenated)."""
        return b"".join(self.packets_to_send())

    # ---- connection and gate ----------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """True while the shell has a transport (nothing is written otherwise)."""
        return self._connected

    def connection_lost(self, now: float, error: ViscaError) -> list[SessionEvent]:
        """The transport is gone: fail every waiter with ``error``, forget socket state."""
        self._expire(now)
        self._connected = False
        self._addressed = False
        self._outgoing.clear()
        self._fail_everything(error, now)
        return self._take_events()

    def connection_made(self, now: float) -> None:
        """A (new) transport is up: stale partial input is dropped, queued requests may go."""
        self._expire(now)
        self._connected = True
        self._reassembler.clear()
        self._pump_all(now)

    @property
    def gated(self) -> bool:
        """True while only privileged requests go out (re-initialisation in progress)."""
        return self._gated

    def close_gate(self) -> None:
        """Hold every request not submitted as privileged (re-initialisation begins)."""
        self._gated = True

    def open_gate(self, now: float) -> None:
        """Let every request go again (re-initialisation over)."""
        self._expire(now)
        self._gated = False
        self._pump_all(now)

    def mark_addressed(self) -> None:
        """The chain was addressed: a later Network Change is unexpected (logged as a warning)."""
        self._addressed = True

    # ---- camera state -----------------------------------------------------------------------

    def set_max_sockets(self, address: int, sockets: int) -> None:
        """Limit commands in flight for ``address`` (VersionInq's KK; 1 or 2)."""
        check_range("max sockets", sockets, 1, SOCKETS_PER_CAMERA)
        self._camera(address).max_sockets = sockets

    def running(self, address: int) -> dict[int, Command]:
        """Commands in flight for ``address`` by socket (as the session believes)."""
        cam = self._cameras.get(address)
        return {} if cam is None else {s: e.request for s, e in cam.sockets.items()}

    def pending(self) -> int:
        """Requests not yet finished (queued or in flight)."""
        return len(self._live)

    def stats(self) -> SessionStats:
        """A snapshot of the counters."""
        return SessionStats(
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
            last_reply_t=self._last_reply,
        )

    # ---- internals: submitting --------------------------------------------------------------

    def _ticket(self) -> int:
        ticket = self._next_ticket
        self._next_ticket += 1
        return ticket

    def _submit_command(
        self,
        cam: _CameraState,
        command: Command,
        now: float,
        *,
        priority: bool | None,
        completion_timeout: float | None,
        privileged: bool,
    ) -> int:
        if len(cam.queue) >= COMMAND_QUEUE_MAX:
            raise LinkBusyError(
                f"{len(cam.queue)} commands already queued for camera {cam.address}: wait for "
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
            ticket=self._ticket(),
            address=cam.address,
            request=command,
            completion_timeout=timeout,
            privileged=privileged,
            deadline=now + self.timeouts.queue_s,
        )
        if priority:
            cam.queue.appendleft(entry)
        else:
            cam.queue.append(entry)
        self._live[entry.ticket] = entry
        logger.debug("camera %d: queued %s (priority=%s)", cam.address, entry.name, priority)
        self._pump(cam, now)
        return entry.ticket

    def _submit_inquiry(
        self, cam: _CameraState, inquiry: InquiryLike, now: float, privileged: bool
    ) -> int:
        if len(cam.inquiries) >= INQUIRY_QUEUE_MAX:
            raise LinkBusyError(
                f"{len(cam.inquiries)} inquiries already queued for camera {cam.address}: "
                "poll less often"
            )
        entry = _InquiryEntry(
            ticket=self._ticket(),
            address=cam.address,
            request=inquiry,
            privileged=privileged,
            deadline=now + self.timeouts.queue_s,
        )
        cam.inquiries.append(entry)
        self._live[entry.ticket] = entry
        self._pump(cam, now)
        return entry.ticket

    def _submit_cancel(self, cam: _CameraState, socket: int, now: float) -> int:
        ticket = self._ticket()
        pending = cam.cancels.get(socket)
        if pending is None:
            pending = self._send_cancel(cam, socket, now)
        pending.tickets.append(ticket)
        self._live[ticket] = pending
        return ticket

    def _submit_broadcast(self, request: Broadcast, now: float) -> int:
        if len(self._broadcasts) >= BROADCAST_QUEUE_MAX:
            raise LinkBusyError(
                f"{len(self._broadcasts)} broadcasts already queued on {self.name}: "
                "wait for the chain to be addressed"
            )
        entry = _BroadcastEntry(
            ticket=self._ticket(), request=request, deadline=now + self.timeouts.queue_s
        )
        self._broadcasts.append(entry)
        self._live[entry.ticket] = entry
        self._pump_broadcast(now)
        return entry.ticket

    # ---- internals: sending -----------------------------------------------------------------

    def _pump_all(self, now: float) -> None:
        self._pump_broadcast(now)
        for cam in list(self._cameras.values()):
            self._pump(cam, now)

    def _pump_broadcast(self, now: float) -> None:
        if not self._connected or self._broadcast_pending is not None or not self._broadcasts:
            return
        entry = self._broadcasts.popleft()
        entry.deadline = now + self.timeouts.broadcast_s
        self._broadcast_pending = entry
        self._write(encode_request(entry.request, BROADCAST_ADDRESS), entry.name)

    def _pump(self, cam: _CameraState, now: float) -> None:
        """Write whatever may be written now for ``cam``."""
        if not self._connected:
            return
        inquiry = self._eligible(cam.inquiries)
        if cam.inquiry_pending is None and inquiry is not None and now >= cam.inquiry_guard_until:
            cam.inquiries.remove(inquiry)
            inquiry.deadline = now + self.timeouts.inquiry_s
            cam.inquiry_pending = inquiry
            cam.first_reply.append(inquiry)
            self._write(_encode(inquiry.request, cam.address), inquiry.name)
        entry = self._eligible(cam.queue)
        if (
            cam.awaiting_ack is None
            and entry is not None
            and len(cam.sockets) < cam.max_sockets
            and now >= cam.hold_until
            and now >= cam.command_guard_until
        ):
            cam.queue.remove(entry)
            entry.deadline = now + self.timeouts.ack_s
            cam.awaiting_ack = entry
            cam.first_reply.append(entry)
            self._write(_encode(entry.request, cam.address), entry.name)

    def _wake_time(self, cam: _CameraState) -> float | None:
        """When a held request of ``cam`` may go (guard or buffer-full hold), if one waits."""
        if not self._connected:
            return None
        times: list[float] = []
        if cam.inquiry_pending is None and self._eligible(cam.inquiries) is not None:
            times.append(cam.inquiry_guard_until)
        if (
            cam.awaiting_ack is None
            and len(cam.sockets) < cam.max_sockets
            and self._eligible(cam.queue) is not None
        ):
            times.append(max(cam.hold_until, cam.command_guard_until))
        return min(times, default=None)

    def _eligible(self, entries: deque[EntryT]) -> EntryT | None:
        """The next entry that may go now (while gated: the first privileged one)."""
        if not self._gated:
            return entries[0] if entries else None
        return next((e for e in entries if e.privileged), None)

    def _send_cancel(self, cam: _CameraState, socket: int, now: float) -> _CancelEntry:
        entry = _CancelEntry(
            address=cam.address, socket=socket, deadline=now + self.timeouts.cancel_s
        )
        cam.cancels[socket] = entry
        if self._connected:
            self._write(_encode(Cancel(socket), cam.address), entry.name)
        return entry

    def _write(self, data: bytes, what: str) -> None:
        self._outgoing.append(data)
        self._bytes_out += len(data)
        self._packets_out += 1
        logger.debug("%s: send %s: %s", self.name, what, data.hex(" "))

    # ---- internals: receiving ---------------------------------------------------------------

    def _on_packet(self, raw: bytes, now: float) -> None:
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
        self._last_reply = now
        logger.debug("received from %d: %r", packet.sender, reply)
        if isinstance(reply, AddressSetReply | BroadcastEcho):
            self._on_broadcast_reply(reply, now)
            return
        if isinstance(reply, NetworkChange):
            self._on_network_change(packet.sender, now)
            return
        cam = self._camera_for_reply(packet.sender)
        if cam is None:
            self._stray += 1
            logger.debug("reply from unknown camera %d dropped: %r", packet.sender, reply)
            return
        if isinstance(reply, Ack):
            self._on_ack(cam, reply.socket, now)
        elif isinstance(reply, Completion):
            self._on_completion(cam, reply.socket, now)
        elif isinstance(reply, ErrorReply):
            self._on_error(cam, reply.socket, reply.code, now)
        elif isinstance(reply, InquiryReply):
            self._on_inquiry_reply(cam, reply.data, now)

    def _camera_for_reply(self, sender: int) -> _CameraState | None:
        cam = self._cameras.get(sender)
        if cam is not None:
            return cam
        # Firmware quirk (docs/design.md, VISCA facts): some cameras answer from A0 (address 2)
        # instead of 90. With a single camera on the line there is no ambiguity: route it there.
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
                    self.name,
                )
            return only
        return None

    def _on_ack(self, cam: _CameraState, socket: int, now: float) -> None:
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
            self._finish_command(cam, previous, None, now)
        _discard(cam.first_reply, entry)
        cam.awaiting_ack = None
        entry.socket = socket
        entry.deadline = now + entry.completion_timeout
        cam.sockets[socket] = entry
        self._events.append(Acked(entry.ticket, now, socket))

    def _on_completion(self, cam: _CameraState, socket: int, now: float) -> None:
        entry = cam.sockets.get(socket)
        if entry is None:
            # Late (its command timed out) or duplicated: never give it to another command.
            self._stray += 1
            logger.debug("camera %d: stray Completion for idle socket %d", cam.address, socket)
            return
        self._finish_command(cam, entry, None, now)

    def _on_error(self, cam: _CameraState, socket: int, code: int, now: float) -> None:
        self._errors[code] += 1
        if code in (ErrorCode.CANCELLED, ErrorCode.NO_SOCKET):
            handled = False
            pending = cam.cancels.pop(socket, None)
            if pending is not None:
                self._resolve_cancel(pending, code == ErrorCode.CANCELLED, now)
                handled = True
            running = cam.sockets.get(socket)
            if code == ErrorCode.CANCELLED and running is not None:
                self._finish_command(
                    cam, running, error_from_reply(code, socket, cam.address, running.name), now
                )
                handled = True
            if not handled:
                self._stray += 1
                logger.debug("camera %d: stray cancel reply %02X/%d", cam.address, code, socket)
            return
        target: _CommandEntry | _InquiryEntry | None
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
                cam, target, error_from_reply(code, socket, cam.address, target.name), None, now
            )
            return
        if target is cam.awaiting_ack:
            _discard(cam.first_reply, target)
            cam.awaiting_ack = None
            if code == ErrorCode.BUFFER_FULL and self._retry_buffer_full(cam, target, now):
                return
        self._finish_command(
            cam, target, error_from_reply(code, socket, cam.address, target.name), now
        )

    def _retry_buffer_full(self, cam: _CameraState, entry: _CommandEntry, now: float) -> bool:
        if entry.retries >= self.timeouts.buffer_full_retries:
            return False
        entry.retries += 1
        self._buffer_full_retries += 1
        if len(cam.sockets) < cam.max_sockets:
            # The camera has more commands than the session knows of (a lost ACK left one
            # running): cancel the sockets believed idle so both are known free.
            self._resyncs += 1
            logger.debug("camera %d: buffer full with free sockets; cancelling them", cam.address)
            for socket in range(1, SOCKETS_PER_CAMERA + 1):
                if socket not in cam.sockets and socket not in cam.cancels:
                    self._send_cancel(cam, socket, now)
        cam.queue.appendleft(entry)
        entry.deadline = now + self.timeouts.queue_s
        cam.hold_until = now + self.timeouts.buffer_full_backoff_s
        logger.debug(
            "camera %d: buffer full; retry %d of %s", cam.address, entry.retries, entry.name
        )
        return True

    def _on_inquiry_reply(self, cam: _CameraState, data: bytes, now: float) -> None:
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
        self._finish_inquiry(cam, entry, None, answer, now)

    def _on_broadcast_reply(self, reply: AddressSetReply | BroadcastEcho, now: float) -> None:
        entry = self._broadcast_pending
        if entry is not None:
            if isinstance(reply, AddressSetReply):
                match = isinstance(entry.request, AddressSet)
            else:
                match = reply.message == entry.request.to_message()
            if match:
                self._broadcast_pending = None
                del self._live[entry.ticket]
                self._events.append(Answered(entry.ticket, now, reply))
                return
        self._stray += 1
        logger.debug("stray broadcast reply %r", reply)

    def _on_network_change(self, sender: int, now: float) -> None:
        self._network_changes += 1
        # Before the chain was first addressed this is just a camera powering up as we connect.
        logger.log(
            logging.WARNING if self._addressed else logging.INFO,
            "camera %d on %s reported a Network Change (power cycle or re-cabling): "
            "re-addressing the chain",
            sender,
            self.name,
        )
        self._addressed = False
        self._gated = True
        self._fail_everything(
            ViscaNetworkChangeError(
                f"camera {sender} on {self.name} reported a Network Change while the request "
                "was pending; the camera is being re-initialised, issue the request again"
            ),
            now,
        )
        self._events.append(NetworkChanged(now, sender))

    # ---- internals: completing --------------------------------------------------------------

    def _finish_command(
        self, cam: _CameraState, entry: _CommandEntry, error: ViscaError | None, now: float
    ) -> None:
        if entry.socket is not None and cam.sockets.get(entry.socket) is entry:
            del cam.sockets[entry.socket]
        if cam.awaiting_ack is entry:
            cam.awaiting_ack = None
        _discard(cam.first_reply, entry)
        self._live.pop(entry.ticket, None)
        if error is None:
            self._events.append(Completed(entry.ticket, now))
            logger.debug("camera %d: %s completed", cam.address, entry.name)
            # A socket just freed: a command held back by buffer-full may go now.
            cam.hold_until = -math.inf
        else:
            self._events.append(Failed(entry.ticket, now, error))
            logger.debug("camera %d: %s failed: %s", cam.address, entry.name, error)

    def _finish_inquiry(
        self,
        cam: _CameraState,
        entry: _InquiryEntry,
        error: ViscaError | None,
        answer: InquiryData | None,
        now: float,
    ) -> None:
        if cam.inquiry_pending is entry:
            cam.inquiry_pending = None
        _discard(cam.first_reply, entry)
        self._live.pop(entry.ticket, None)
        if error is None:
            self._events.append(Answered(entry.ticket, now, answer))
        else:
            self._events.append(Failed(entry.ticket, now, error))

    def _resolve_cancel(self, entry: _CancelEntry, cancelled: bool, now: float) -> None:
        for ticket in entry.tickets:
            self._live.pop(ticket, None)
            self._events.append(Answered(ticket, now, cancelled))
        entry.tickets.clear()

    def _fail_everything(self, error: ViscaError, now: float) -> None:
        """Fail every waiter (transport lost or chain reset) and forget the socket state."""
        for cam in self._cameras.values():
            entries: list[_CommandEntry | _InquiryEntry] = [
                *cam.queue,
                *cam.inquiries,
                *cam.sockets.values(),
            ]
            if cam.awaiting_ack is not None:
                entries.append(cam.awaiting_ack)
            if cam.inquiry_pending is not None:
                entries.append(cam.inquiry_pending)
            cancels = list(cam.cancels.values())
            cam.reset()
            for entry in entries:
                self._live.pop(entry.ticket, None)
                self._events.append(Failed(entry.ticket, now, error))
            for cancel in cancels:
                for ticket in cancel.tickets:
                    self._live.pop(ticket, None)
                    self._events.append(Failed(ticket, now, error))
        broadcasts = list(self._broadcasts)
        if self._broadcast_pending is not None:
            broadcasts.insert(0, self._broadcast_pending)
        self._broadcasts.clear()
        self._broadcast_pending = None
        for broadcast in broadcasts:
            self._live.pop(broadcast.ticket, None)
            self._events.append(Failed(broadcast.ticket, now, error))

    # ---- internals: deadlines ---------------------------------------------------------------

    def _deadlines(self) -> list[tuple[float, _Waiting]]:
        """Every armed wait: (deadline, what expires)."""
        out: list[tuple[float, _Waiting]] = []
        for cam in self._cameras.values():
            out.extend((e.deadline, ("queue", cam, e)) for e in cam.queue)
            out.extend((e.deadline, ("inquiry queue", cam, e)) for e in cam.inquiries)
            if cam.awaiting_ack is not None:
                out.append((cam.awaiting_ack.deadline, ("ACK", cam, cam.awaiting_ack)))
            out.extend((e.deadline, ("Completion", cam, e)) for e in cam.sockets.values())
            if cam.inquiry_pending is not None:
                out.append(
                    (cam.inquiry_pending.deadline, ("inquiry reply", cam, cam.inquiry_pending))
                )
            out.extend((e.deadline, ("cancel reply", cam, e)) for e in cam.cancels.values())
        out.extend((b.deadline, ("broadcast queue", None, b)) for b in self._broadcasts)
        if self._broadcast_pending is not None:
            pending = self._broadcast_pending
            out.append((pending.deadline, ("broadcast reply", None, pending)))
        return out

    def _expire(self, now: float) -> None:
        """Run every wait that expired by ``now`` in time order, each at its own time."""
        while True:
            times = self._times()
            # Nothing happens before the time of the previous call (all of that was handled).
            t = max(min(times, default=math.inf), self._clock)
            if t > now:
                break
            self._clock = t  # processing has reached t: nothing may happen before it
            sent = len(self._outgoing)
            self._pump_all(t)  # requests a guard or hold released by ``t`` go first
            due = [(d, w) for d, w in self._deadlines() if d <= t]
            if due:
                self._on_deadline(min(due, key=lambda item: item[0])[1], t)
            elif len(self._outgoing) == sent:
                break  # a wake-up with nothing to release (cannot happen; never spin)
        self._clock = max(self._clock, now)

    def _times(self) -> list[float]:
        """Every deadline and every time a held request may go."""
        times = [d for d, _ in self._deadlines()]
        times += [w for cam in self._cameras.values() if (w := self._wake_time(cam)) is not None]
        return times

    def _on_deadline(self, waiting: _Waiting, t: float) -> None:
        kind, cam, entry = waiting
        tm = self.timeouts
        if isinstance(entry, _BroadcastEntry):
            if kind == "broadcast reply":
                self._broadcast_pending = None
                wait, timeout = f"{entry.name} reply", tm.broadcast_s
                self._timeouts["broadcast reply"] += 1
            else:
                self._broadcasts.remove(entry)
                wait, timeout = "turn to send", tm.queue_s
                self._timeouts["queue"] += 1
            self._live.pop(entry.ticket, None)
            self._events.append(Failed(entry.ticket, t, ViscaTimeoutError(wait, timeout)))
            return
        assert cam is not None
        if isinstance(entry, _CancelEntry):
            del cam.cancels[entry.socket]
            self._timeouts["cancel reply"] += 1
            error = ViscaTimeoutError("cancel reply", tm.cancel_s, entry.name, cam.address)
            for ticket in entry.tickets:
                self._live.pop(ticket, None)
                self._events.append(Failed(ticket, t, error))
            return
        if isinstance(entry, _InquiryEntry):
            if kind == "inquiry queue":
                cam.inquiries.remove(entry)
                self._timeouts["queue"] += 1
                error = ViscaTimeoutError("turn to send", tm.queue_s, entry.name, cam.address)
            else:
                self._timeouts["inquiry reply"] += 1
                cam.inquiry_guard_until = t + tm.late_reply_guard_s
                error = ViscaTimeoutError("inquiry reply", tm.inquiry_s, entry.name, cam.address)
            self._finish_inquiry(cam, entry, error, None, t)
            return
        if kind == "queue":
            cam.queue.remove(entry)
            self._timeouts["queue"] += 1
            error = ViscaTimeoutError("free socket", tm.queue_s, entry.name, cam.address)
        elif kind == "ACK":
            self._timeouts["ACK"] += 1
            cam.command_guard_until = t + tm.late_reply_guard_s
            error = ViscaTimeoutError("ACK", tm.ack_s, entry.name, cam.address)
        else:
            self._timeouts["Completion"] += 1
            socket = entry.socket
            # The command may still run (or its Completion was lost): cancel the socket so the
            # camera and the session agree it is free. The Cancel is written before any new
            # command.
            if socket is not None and socket not in cam.cancels and self._connected:
                self._send_cancel(cam, socket, t)
            error = ViscaTimeoutError(
                "Completion", entry.completion_timeout, entry.name, cam.address
            )
        self._finish_command(cam, entry, error, t)

    # ---- internals: helpers -----------------------------------------------------------------

    def _take_events(self) -> list[SessionEvent]:
        events, self._events = self._events, []
        return events

    def _camera(self, address: int) -> _CameraState:
        check_range("camera address", address, MIN_CAMERA_ADDRESS, MAX_CAMERA_ADDRESS)
        cam = self._cameras.get(address)
        if cam is None:
            cam = self._cameras[address] = _CameraState(address)
        return cam


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _encode(request: Command | InquiryLike | Cancel, address: int) -> bytes:
    return Packet(CONTROLLER_ADDRESS, address, request.to_message()).to_bytes()
