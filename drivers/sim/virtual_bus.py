"""The controller's VISCA session wired to the simulated camera, byte for byte, in virtual time.

The lock-step bench drives the same :class:`~drivers.visca.session.ViscaSession` the service's
link runs, against the real device model (:class:`~drivers.sim.device.ViscaDevice`: wire pacing
at the configured baud, one message per video field, two sockets), so every reply is matched by
the service's own rules (one ACK outstanding, Completion per socket, late-Completion guard,
buffer-full retry, cancels, timeouts) and the depth rate the bench measures includes the link as
the simulated camera imposes it. Nothing here reads a clock: the caller passes ``now``.

Usage: ``ticket = bus.submit(request, now)``; at ``bus.next_deadline()`` (or any later time)
``bus.poll(now)`` returns the session's events, each stamped with the virtual time it happened.
A Network Change is answered as the link answers it — Address Set and IF_Clear, then the gate
opens — and still reported, so the caller can forget what the camera lost.
"""

from __future__ import annotations

from drivers.sim.device import ViscaDevice
from drivers.visca.codec_requests import AddressSet, IFClearBroadcast
from drivers.visca.session import ViscaSession
from drivers.visca.session_types import (
    Answered,
    Failed,
    LinkTimeouts,
    NetworkChanged,
    SessionEvent,
    SessionRequest,
    SessionStats,
)


class VirtualBus:
    """A :class:`ViscaSession` and a :class:`ViscaDevice` connected in virtual time."""

    def __init__(
        self,
        device: ViscaDevice,
        *,
        timeouts: LinkTimeouts | None = None,
        address: int = 1,
    ) -> None:
        self.device = device
        self.address = address
        self.session = ViscaSession(timeouts, name="virtual VISCA bus")
        self._readdress: list[int] = []  # tickets of the re-addressing broadcasts in flight

    def submit(
        self,
        request: SessionRequest,
        now: float,
        *,
        priority: bool | None = None,
        completion_timeout: float | None = None,
    ) -> int:
        """Queue ``request`` for the camera at ``now``; return its ticket (see ViscaSession)."""
        ticket = self.session.submit(
            request,
            now,
            address=self.address,
            priority=priority,
            completion_timeout=completion_timeout,
        )
        self._deliver(now)
        return ticket

    def next_deadline(self) -> float | None:
        """When the session or the device next has something to do, or None."""
        candidates = (self.session.next_deadline(), self.device.next_deadline())
        times = [t for t in candidates if t is not None]
        return min(times) if times else None

    def poll(self, now: float) -> list[SessionEvent]:
        """Advance both sides to ``now``; return the session's events in time order."""
        events: list[SessionEvent] = []
        while (t := self.next_deadline()) is not None and t <= now:
            events.extend(self._step(t))
        events.extend(self._step(now))
        return events

    def stats(self) -> SessionStats:
        """The session's counters (bytes, replies, errors, timeouts, strays…)."""
        return self.session.stats()

    # ---- internals ----------------------------------------------------------------------------

    def _step(self, t: float) -> list[SessionEvent]:
        events: list[SessionEvent] = []
        for emission in self.device.poll(t):
            events.extend(self._handle(self.session.receive(emission.data, emission.t)))
            self._deliver(emission.t)
        events.extend(self._handle(self.session.poll(t)))
        self._deliver(t)
        return events

    def _deliver(self, t: float) -> None:
        data = self.session.data_to_send()
        if data:
            self.device.receive(data, t)

    def _handle(self, events: list[SessionEvent]) -> list[SessionEvent]:
        out: list[SessionEvent] = []
        for event in events:
            if isinstance(event, NetworkChanged):
                # As the link does: re-address the chain; the gate opens once it is done. (A
                # re-addressing cut short by this change already ended in the events before.)
                self.session.close_gate()
                self._readdress = [
                    self.session.submit(AddressSet(), event.t),
                    self.session.submit(IFClearBroadcast(), event.t),
                ]
            elif isinstance(event, Answered | Failed) and event.ticket in self._readdress:
                self._readdress.remove(event.ticket)
                if not self._readdress:
                    self.session.open_gate(event.t)
                continue
            out.append(event)
        return out
