"""The simulator's virtual clock: time that moves only when told to."""

from __future__ import annotations


class VirtualClock:
    """A clock that only moves when told to: lock-step tests and fast benchmarks."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = start

    def __call__(self) -> float:
        """The current virtual time in seconds."""
        return self._now

    def set(self, t: float) -> None:
        """Move to ``t`` (never backwards)."""
        if t < self._now:
            raise ValueError(f"virtual clock cannot go back from {self._now} to {t}")
        self._now = t

    def advance(self, dt: float) -> float:
        """Move forward by ``dt`` seconds; return the new time."""
        self.set(self._now + dt)
        return self._now
