"""The simulated camera's models (EVI-D100, EVI-D70, SRG-300-like) through the camera API.

The driver's profiles (drivers/visca/profiles.py) and the simulator's models
(drivers/sim/models.py) are written separately; here the driver, configured as an EVI-D100,
meets each simulated model over the transport that model is used on (the EVIs on a pty, the SRG
over VISCA over IP), identifies it by its version inquiry, takes its profile, and then reaches
that model's end stops and focus range — and is refused one step beyond them before sending.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

import pytest

from drivers.sim.device_types import DeviceConfig
from drivers.sim.ip_server import SimUdpServer
from drivers.sim.models import SIM_MODELS, SimModel, sim_model
from drivers.sim.server import SimCameraServer
from drivers.visca.camera import EVI_D100, PROFILES, Camera
from drivers.visca.link import ViscaLink
from tests.visca_support import FAST

# Where each model is exercised: the serial EVIs on a pty, the IP head over UDP.
TRANSPORT = {"evi-d100": "pty", "evi-d70": "pty", "srg-300": "udp"}
# Pan/tilt positions are whole counts (13.3–14.4 per degree): within 0.1° of the target.
POSITION_TOL_DEG = 0.1


@contextlib.asynccontextmanager
async def _camera(model: SimModel, transport: str) -> AsyncIterator[Camera]:
    # A fast motor (no pacing) keeps full-range moves short; the limits are what is tested.
    config = DeviceConfig(camera=model, focus_speed_counts_s=200_000.0)
    server = SimCameraServer(config) if transport == "pty" else SimUdpServer(config)
    async with server:
        url = server.path if isinstance(server, SimCameraServer) else server.url
        async with ViscaLink(str(url), timeouts=FAST) as link:
            camera = Camera(link, 1, EVI_D100)  # configured as a D100 whatever it is
            await camera.initialize()
            yield camera


@pytest.mark.parametrize("name", sorted(SIM_MODELS))
def test_driver_profiles_agree_with_the_simulated_models(name: str) -> None:
    sim, driver = sim_model(name), PROFILES[name]
    assert driver.name == sim.name
    assert driver.pan_range_deg == sim.pan_limits_deg
    assert driver.tilt_range_deg == sim.tilt_limits_deg
    assert driver.focus_range == sim.focus_range
    assert driver.zoom_range == sim.zoom_range
    assert len(driver.pan_speeds_deg_s) == sim.max_pan_speed_code
    assert len(driver.tilt_speeds_deg_s) == sim.max_tilt_speed_code
    assert driver.pan_speeds_deg_s[-1] == pytest.approx(sim.pan_speeds_deg_s[-1])
    assert (sim.vendor, sim.model) in driver.identities


@pytest.mark.parametrize("name", sorted(SIM_MODELS))
async def test_each_model_is_identified_and_driven_to_its_limits(name: str) -> None:
    model = sim_model(name)
    async with _camera(model, TRANSPORT[name]) as camera:
        version = camera.version_info
        assert version is not None
        assert (version.vendor, version.model) == (model.vendor, model.model)
        assert camera.profile.name == model.name  # the camera's own profile, not the config's
        (pan_low, pan_high), (tilt_low, tilt_high) = model.pan_limits_deg, model.tilt_limits_deg
        for pan, tilt in ((pan_high, tilt_high), (pan_low, tilt_low), (0.0, 0.0)):
            await camera.pan_tilt_absolute(pan, tilt)
            got_pan, got_tilt = await camera.pan_tilt_position()
            assert got_pan == pytest.approx(pan, abs=POSITION_TOL_DEG)
            assert got_tilt == pytest.approx(tilt, abs=POSITION_TOL_DEG)
        far, near = model.focus_range
        await camera.focus_direct(near)
        assert await camera.focus_position() == near
        await camera.focus_direct(far)
        sent = camera.link.health().bytes_out
        for call in (
            lambda: camera.pan_tilt_absolute(pan_high + 1.0, 0.0),
            lambda: camera.pan_tilt_absolute(0.0, tilt_low - 1.0),
            lambda: camera.focus_direct(near + 1),
            lambda: camera.pan_tilt_drive(model.pan_speeds_deg_s[-1] * 1.5, 0.0),
        ):
            with pytest.raises(ValueError, match=f"for the {model.name}"):
                await call()
        assert camera.link.health().bytes_out == sent


async def test_a_d100_refuses_what_a_d70_accepts() -> None:
    # The simulated device enforces its own model's limits (a controller that ignores them
    # gets the camera's syntax error, as from the real one).
    from drivers.sim.device import ViscaDevice
    from drivers.sim.state import CameraState
    from drivers.visca import codec, codec_requests

    d100 = ViscaDevice(CameraState(clock=lambda: 0.0), DeviceConfig(camera=sim_model("evi-d100")))
    d70 = ViscaDevice(CameraState(clock=lambda: 0.0), DeviceConfig(camera=sim_model("evi-d70")))
    request = codec_requests.FocusDirect(0xB000)
    packet = codec.encode_request(request, 1)
    replies = []
    for device in (d100, d70):
        device.power_up(0.0)
        device.receive(packet, 1.0)
        replies.append(b"".join(e.data for e in device.poll(3.0)))
    assert b"\x60\x02\xff" in replies[0]  # syntax error
    assert b"\x41\xff" in replies[1] or b"\x51\xff" in replies[1]  # ACK from the D70
