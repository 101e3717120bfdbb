"""One builder of the simulated camera: config → clock, camera state, world, renderer, device.

The daemon (live, on ``time.monotonic``), the lock-step bench and ``dffd calibrate --sim`` (both
in virtual time, on :class:`~drivers.sim.virtual_clock.VirtualClock`, the one virtual clock)
assemble the simulated camera here, so the three cannot drift apart. A runner differs only in its
clock and in how it talks to the device (a pty server, or bytes in virtual time).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from drivers.sim.config import SimCameraConfig
from drivers.sim.device import ViscaDevice
from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import Faults
from drivers.sim.source import SimFrameSource, camera_state_for
from drivers.sim.state import CameraState, Clock
from drivers.sim.virtual_clock import VirtualClock
from drivers.sim.world import World

__all__ = ["SimCamera", "build_sim_camera"]


@dataclass(frozen=True, slots=True)
class SimCamera:
    """A simulated camera looking at its world: every part shares one clock."""

    config: SimCameraConfig
    clock: Clock  # time.monotonic live, a VirtualClock in lock-step
    state: CameraState
    world: World
    source: SimFrameSource
    device_config: DeviceConfig

    @property
    def virtual_clock(self) -> VirtualClock:
        """The virtual clock (TypeError for a live rig)."""
        if not isinstance(self.clock, VirtualClock):
            raise TypeError("this simulated camera runs on the live clock")
        return self.clock

    def device(self, faults: Faults | None = None) -> ViscaDevice:
        """The camera's VISCA device model on this rig's state (optionally with faults)."""
        return ViscaDevice(self.state, self.device_config, faults)


def build_sim_camera(
    config: SimCameraConfig,
    *,
    device: DeviceConfig | None = None,
    virtual_start_s: float | None = None,
    t0: float | None = None,
) -> SimCamera:
    """The simulated camera of ``config``.

    ``virtual_start_s`` given: it runs on a fresh :class:`VirtualClock` starting there;
    otherwise on ``time.monotonic``. ``t0`` is the first exposure's mid-time (default: the
    renderer's). ``device`` configures the VISCA device model (default: ``DeviceConfig()``).
    """
    clock: Clock = time.monotonic if virtual_start_s is None else VirtualClock(virtual_start_s)
    state = camera_state_for(config, clock=clock)
    world = World.from_config(config.world)
    source = SimFrameSource.from_config(config, state, world, t0=t0)
    return SimCamera(config, clock, state, world, source, device or DeviceConfig())
