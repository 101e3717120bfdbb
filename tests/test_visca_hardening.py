"""Driver hardening against the simulated camera on a real pty.

Values are checked against the model's limits before a byte is sent; an error the device returns
for a request the driver validated points at the device (firmware or model), not at the driver;
a device that does not echo the broadcast IF_Clear is still initialised; the model the camera
identifies as picks its profile, with a warning when the configuration names another one.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging

import pytest

from drivers.sim import models as sim_models
from drivers.sim.device_types import DeviceConfig
from drivers.sim.faults import Faults
from drivers.sim.ip_server import SimUdpServer
from drivers.sim.server import SimCameraServer
from drivers.visca.camera import (
    EVI_D70,
    EVI_D100,
    IP_COMPLETION_PROBE_S,
    SRG_300,
    Camera,
    profile_for_version,
)
from drivers.visca.errors import ViscaSyntaxError
from drivers.visca.link import ViscaLink
from tests.visca_support import FAST, sim_camera

# A device that does not echo the broadcast IF_Clear costs one broadcast timeout at start-up.
SILENT_BROADCAST = dataclasses.replace(FAST, broadcast_s=0.2)
# The simulated EVI-D100 identifying as an EVI-D70: the simulator's model code, not the profile's.
REPORTS_EVI_D70 = DeviceConfig(model=sim_models.EVI_D70.model)


# (call, the error it must raise): value, limit and model named.
OUT_OF_RANGE = (
    ("pan_tilt_absolute", (-480.0, 0.0), {},
     r"pan_deg = -480(\.0)?° is out of range \[-100\.0°, 100\.0°\] for the EVI-D100"),
    ("focus_direct", (50_000,), {},
     r"focus counts = 50000 \(0xC350\) is out of range \[0x1000, 0x8400\] for the EVI-D100"),
    ("zoom_direct", (20_000,), {}, r"zoom counts = 20000 .* for the EVI-D100"),
    ("pan_tilt_absolute", (10.0, 0.0), {"speed": 500.0},
     r"speed = 500(\.0)? deg/s is out of range .* for the EVI-D100"),
    ("pan_tilt_drive", (10.0, -400.0), {},
     r"tilt_speed_deg_s = -400(\.0)? deg/s .* for the EVI-D100"),
)  # fmt: skip


async def test_out_of_range_values_are_refused_before_anything_is_sent() -> None:
    async with sim_camera() as (_server, link, camera):
        sent = link.health().bytes_out
        for name, args, kwargs, message in OUT_OF_RANGE:
            with pytest.raises(ValueError, match=message):
                await getattr(camera, name)(*args, **kwargs)
        assert link.health().bytes_out == sent


async def test_a_syntax_error_after_validation_points_at_the_device() -> None:
    # The driver is told the camera is a D70 (focus up to 0xC000) and keeps that profile; the
    # device is a D100 (focus up to 0x8400), which answers a syntax error.
    async with (
        SimCameraServer(DeviceConfig()) as server,
        ViscaLink(server.path, timeouts=FAST) as link,
    ):
        camera = Camera(link, 1, EVI_D70, adopt_profile=False)
        await camera.initialize()
        with pytest.raises(ViscaSyntaxError) as caught:
            await camera.focus_direct(0xB000)
    text = str(caught.value)
    assert "device is the likely side at fault" in text
    assert "checked against the EVI-D70 profile" in text
    assert "vendor 0x0001 model 0x040D, the EVI-D100" in text
    assert "driver bug" not in text
    assert caught.value.code == 0x02


async def test_a_device_that_does_not_echo_the_if_clear_broadcast_is_initialised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.visca.link")
    config = DeviceConfig(echo_if_clear_broadcast=False)
    async with sim_camera(config, timeouts=SILENT_BROADCAST) as (server, link, camera):
        assert await camera.focus_position() > 0
        await camera.focus_direct(0x2000)
        assert await camera.focus_position() == 0x2000
    assert "broadcast IF_Clear was not echoed" in caplog.text
    assert link.chain_length == 1
    assert server.device.stats.packets_in > 0


async def test_the_model_the_camera_reports_picks_its_profile(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.visca.camera")
    async with sim_camera(REPORTS_EVI_D70, profile=EVI_D100) as (_, _, camera):
        assert camera.profile is EVI_D70
        assert camera.version_info is not None
    assert "identifies as the EVI-D70" in caplog.text
    assert "set camera.model = 'evi-d70'" in caplog.text


async def test_the_daemon_refuses_a_camera_of_another_model_than_configured() -> None:
    """The daemon's scheduler is built from camera.model; a camera identifying as another known
    model would have its pan/tilt speeds chosen on one table and sent on another: start-up
    says which model to configure instead. The configured model, or an unknown one, passes."""
    from dffd.daemon.startup import camera_model_problem

    async with sim_camera(REPORTS_EVI_D70, profile=EVI_D100) as (_, _, camera):
        problem = camera_model_problem(camera, "evi-d100")
        assert camera_model_problem(camera, "evi-d70") is None
    assert problem is not None
    assert "identifies as the EVI-D70 but camera.model is 'evi-d100'" in problem
    assert problem.endswith("set camera.model = 'evi-d70'")
    async with sim_camera(DeviceConfig(model=0x0777), profile=EVI_D100) as (_, _, camera):
        assert camera_model_problem(camera, "evi-d100") is None


async def test_an_unknown_model_keeps_the_configured_profile_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.visca.camera")
    async with sim_camera(DeviceConfig(model=0x0777), profile=EVI_D100) as (_, _, camera):
        assert camera.profile is EVI_D100
    assert "model 0x0777, which dffd has no profile for" in caplog.text


def test_identities_map_to_profiles() -> None:
    assert profile_for_version(0x0001, 0x040D) is EVI_D100
    assert profile_for_version(0x0020, 0x040E) is EVI_D70  # FCB-style Sony vendor ID
    assert profile_for_version(0x0001, 0x0516) is SRG_300
    assert profile_for_version(0x0001, 0x7777) is None


async def test_a_lost_completion_over_visca_ip_is_recovered_by_inquiry() -> None:
    # Every Completion is lost; over VISCA over IP the camera API asks where the lens and the
    # head are after IP_COMPLETION_PROBE_S of silence and takes a move at its target as done,
    # long before the move's own Completion timeout (3.5 s for a focus move).
    config = DeviceConfig(network_change_at_power_up=False, focus_speed_counts_s=0x7400 / 0.3)
    async with (
        SimUdpServer(config) as server,
        ViscaLink(server.url, timeouts=FAST) as link,
    ):
        camera = Camera(link, 1, EVI_D100)
        await camera.initialize()
        server.device.faults = Faults("seed=1,lose_completion=1.0")  # from now on
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        await camera.focus_direct(0x3000)
        await camera.pan_tilt_absolute(12.5, -4.0)
        elapsed = loop.time() - t0
        assert await camera.focus_position() == 0x3000
        pan, tilt = await camera.pan_tilt_position()
        assert (pan, tilt) == (pytest.approx(12.5, abs=0.1), pytest.approx(-4.0, abs=0.1))
        assert camera.completions_inferred == 2
        assert link.health().lost_completions >= 2
        assert link.health().timeouts.get("Completion", 0) == 0
    # Two moves, each found over at the first or second probe: well under one focus timeout.
    assert elapsed < 4 * IP_COMPLETION_PROBE_S + 1.0
