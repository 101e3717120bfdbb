"""The first-depth gate: when the core's depths may be published after a start or a loss.

One gate for every runner (:class:`dffd.step.CoreStep` owns it): the daemon publishes, the bench
scores and ``dffd replay`` writes and summarises the same estimates (docs/design.md §8).

After a start or a loss the core initialises its filters from the first accepted burst, also
when its vertex lay outside the bracket (extrapolated). The first burst of a start spans most of
the focus range, where the cost is far from a parabola: live on the default demo its
extrapolated vertex put the target at 15.2 m (σ 0.76 m) while it was at 10.0 m, and the first
four estimates said 14.4-15.1 m with σ 0.72-0.75 m (a 6-7σ error). So depths are published only
once a burst with its vertex inside its bracket has been taken (or :data:`FIRST_DEPTH_MAX_BURSTS`
accepted bursts, so a target that keeps outrunning its brackets is not hidden for ever); until
then estimates go out with their depth fields null. The ``…/measurement`` payloads of those
bursts are published as they are, with their reason. The first burst's vertex can also fall
*inside* its (full-range) bracket and far from the target: after a release and an automatic
re-acquisition on the demo it read 10.5 m for a target at 8.1 m and the first estimate said
11.6 m — with σ 18 m. So the gate also waits until the best estimate's own σ is at most its
depth (:data:`FIRST_DEPTH_MAX_REL_SIGMA`: a depth whose 1σ exceeds it does not even say its order
of magnitude), or :data:`FIRST_DEPTH_FORCE_BURSTS` accepted bursts. The first depths of normal
starts pass at once: σ 0.17-0.19 m at 9.8 m on the demo, 1.05 m at 3.97 m on the static world
(the filters' start-up σ; 26 %).

Pure: no I/O, no clock.
"""

from __future__ import annotations

from dffd.core.focus import REASON_OK
from dffd.core.outputs import Estimate, Measurement

__all__ = [
    "FIRST_DEPTH_FORCE_BURSTS",
    "FIRST_DEPTH_MAX_BURSTS",
    "FIRST_DEPTH_MAX_REL_SIGMA",
    "FirstDepthGate",
]

# Accepted bursts after which depths are published even if every one was extrapolated: the
# scheduler centres each next bracket on the last vertex, so on the default demo the second
# burst already brackets it (measured: 1 extrapolated first burst per start, none after).
FIRST_DEPTH_MAX_BURSTS = 3
# The first published depth's 1σ is at most this fraction of it (normal starts: 2-26 %; the wild
# first burst above: 157 %), unless this many bursts were accepted (~3 s of bursts).
FIRST_DEPTH_MAX_REL_SIGMA = 1.0
FIRST_DEPTH_FORCE_BURSTS = 6


class FirstDepthGate:
    """Whether the core's depths may be published yet (see the module docstring)."""

    def __init__(self) -> None:
        self.open = False
        self._bracketed = False  # a burst inside its bracket (or enough bursts) since reset
        self._accepted = 0  # accepted bursts since the filters were (re)initialised
        self.withheld = 0  # estimates with depths whose depths were held back, since start

    def on_measurement(self, m: Measurement) -> None:
        """A burst closed: an accepted one inside its bracket readies the gate."""
        if not m.accepted:
            return
        self._accepted += 1
        if m.reason in ("", REASON_OK) or self._accepted >= FIRST_DEPTH_MAX_BURSTS:
            self._bracketed = True

    def passes(self, est: Estimate) -> bool:
        """True when ``est``'s depths may be published; an estimate without depths (filters
        not initialised: start, loss, release) closes the gate again."""
        if all(z is None for z in est.depth_m.values()):
            self.open = self._bracketed = False
            self._accepted = 0
            return True
        if not self.open and self._bracketed:
            z, sigma = est.z_m, est.sigma_m
            precise = z is not None and sigma is not None and sigma <= FIRST_DEPTH_MAX_REL_SIGMA * z
            self.open = precise or self._accepted >= FIRST_DEPTH_FORCE_BURSTS
        if not self.open:
            self.withheld += 1
        return self.open
