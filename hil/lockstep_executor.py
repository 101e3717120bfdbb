"""The lock-step runner's executor: scheduler actions on the service's VISCA session in virtual
time (:class:`drivers.sim.virtual_bus.VirtualBus`), translated as the daemon translates them
(:func:`dffd.actuation.request_for`), and the session's events back as outcomes
(:mod:`hil.lockstep`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from dffd.actuation import completion_timeout_s, request_for
from dffd.scheduler import Action
from drivers.sim.virtual_bus import VirtualBus
from drivers.visca.camera import MOVE_TIMEOUT_MARGIN_S, CameraProfile
from drivers.visca.session_types import Answered, Completed, Failed, NetworkChanged

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ActionOutcome:
    """How ``action`` ended at ``t``: done (with an inquiry's ``answer``) or failed."""

    action: Action
    t: float
    ok: bool
    answer: object = None


class ActionExecutor:
    """Scheduler actions on the VISCA session in virtual time: the service's translation
    (:func:`dffd.actuation.request_for`) in, the session's events out as outcomes.

    All reply matching is the session's (:mod:`drivers.visca.session`); this only remembers
    which action each ticket carries.
    """

    def __init__(
        self, bus: VirtualBus, profile: CameraProfile, on_network_change: Callable[[float], None]
    ) -> None:
        self.bus = bus
        self.profile = profile
        self._on_network_change = on_network_change  # the bus re-addressed the camera
        self._actions: dict[int, Action] = {}
        self.commands_sent = 0

    def send(self, action: Action, now: float) -> list[ActionOutcome]:
        """Submit ``action`` at ``now`` (one outside the camera's ranges fails at once)."""
        try:
            request = request_for(action, self.profile)
        except ValueError as exc:
            logger.debug("action %r not sent: %s", action, exc)
            return [ActionOutcome(action, now, ok=False)]
        timeout = completion_timeout_s(request, self.profile, MOVE_TIMEOUT_MARGIN_S)
        ticket = self.bus.submit(request, now, completion_timeout=timeout)
        self._actions[ticket] = action
        self.commands_sent += 1
        return []

    def next_deadline(self) -> float | None:
        """When the session or the device next has something to do."""
        return self.bus.next_deadline()

    def poll(self, now: float) -> list[ActionOutcome]:
        """Advance to ``now``; the outcomes of finished actions, in time order."""
        outcomes: list[ActionOutcome] = []
        for event in self.bus.poll(now):
            if isinstance(event, NetworkChanged):
                self._on_network_change(event.t)
                continue
            if not isinstance(event, Completed | Answered | Failed):
                continue  # Acked: the command runs
            action = self._actions.pop(event.ticket, None)
            if action is None:
                continue
            if isinstance(event, Failed):
                logger.debug("VISCA %r failed at %.3f: %s", action, event.t, event.error)
                outcomes.append(ActionOutcome(action, event.t, ok=False))
            else:
                answer = event.value if isinstance(event, Answered) else None
                outcomes.append(ActionOutcome(action, event.t, ok=True, answer=answer))
        return outcomes
