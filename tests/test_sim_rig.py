"""The one builder of the simulated camera: every part on one clock, live or virtual."""

from __future__ import annotations

import time

import pytest

from drivers.sim.config import SimCameraConfig, with_overrides
from drivers.sim.device_types import DeviceConfig
from drivers.sim.rig import build_sim_camera
from drivers.sim.virtual_clock import VirtualClock


def _config() -> SimCameraConfig:
    return with_overrides(
        SimCameraConfig(),
        {"world.trajectory": {"kind": "static", "position_m": (0.0, 0.0, 3.0)}, "seed": 4},
    )


def test_a_virtual_rig_shares_one_virtual_clock() -> None:
    rig = build_sim_camera(_config(), virtual_start_s=0.0, t0=0.5)
    clock = rig.virtual_clock
    assert isinstance(clock, VirtualClock)
    assert rig.state.now() == 0.0
    assert rig.source.frame_time(0) == 0.5
    clock.set(0.75)
    assert rig.state.now() == 0.75  # the state reads the rig's clock
    rig.state.focus.move_to(0x3000, speed=10_000.0, t=0.75)
    device = rig.device()
    assert device.state is rig.state  # the VISCA device moves the same motors
    with pytest.raises(ValueError, match="back"):
        clock.set(0.5)  # virtual time never runs backwards


def test_rendering_is_deterministic_for_a_seed() -> None:
    a = build_sim_camera(_config(), virtual_start_s=0.0, t0=0.5)
    b = build_sim_camera(_config(), virtual_start_s=0.0, t0=0.5)
    for rig in (a, b):
        rig.virtual_clock.set(rig.source.delivery_time(3))
    assert (a.source.render_frame(3).image == b.source.render_frame(3).image).all()
    assert a.source.truth_for(3) == b.source.truth_for(3)


def test_a_live_rig_runs_on_the_monotonic_clock() -> None:
    device = DeviceConfig(baud=38400, pace=True)
    rig = build_sim_camera(_config(), device=device)
    assert rig.clock is time.monotonic
    assert rig.device_config is device
    assert abs(rig.source.t0 - time.monotonic()) < 5.0  # first exposure: now
    with pytest.raises(TypeError, match="live clock"):
        _ = rig.virtual_clock
