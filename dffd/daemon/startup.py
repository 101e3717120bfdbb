"""The daemon's start-up pieces: embedded broker, camera transport, frame source, camera init.

Without ``--config`` (or with ``camera.driver = "sim"``) the camera is the simulator: its VISCA
device on a real pty (:class:`~drivers.sim.server.SimCameraServer`) or on UDP/TCP
(``sim.visca_transport``), served from a thread of its own (:mod:`dffd.daemon.simthread`), its
renderer as the frame source, ground truth on ``…/sim/truth``;
``mqtt.url = "embedded"`` starts the embedded amqtt broker on 127.0.0.1. The world is
``sim.scenario``'s ``[target]`` and ``[trajectory]`` tables (a world shipped in
``drivers/sim/data/worlds/``, or a file path) applied to the simulated camera's own config types
(``drivers.sim.config``), ``sim.start_phase_deg`` overriding the start phase (the default demo
starts the circle at its far point). With a config naming a serial port, a video device
(``[capture]`` → :class:`drivers.capture.OpenCVFrameSource`) and a broker it is the lab service.

Each piece enters what it starts into the daemon's ``AsyncExitStack`` and returns what the
daemon keeps; failures the user can fix raise :class:`DaemonError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from dffd.config import DffdConfig
from dffd.core.lens import Lens
from dffd.daemon.simthread import SimThread
from dffd.scheduler import Scheduler
from dffd.wiring import WiringError, capture_source, sim_camera_config, stream_source
from drivers.frames import FrameSource, FrameSourceError
from drivers.stream import StreamFrameSource
from drivers.visca.camera import Camera, profile_for
from drivers.visca.errors import ViscaError
from drivers.visca.session_types import LinkTimeouts

_LOGGER = logging.getLogger(__name__)

# Camera initialisation: Address Set, IF_Clear, power (the D100 takes ~10 s from standby), zoom.
CAMERA_INIT_TIMEOUT_S = 30.0
# The link's waits for the simulated camera. The hardware's 0.3 s (drivers.visca.session_types)
# are ~3x a busy camera's answer, but the simulator answers from a thread of this process: with
# a browser rendering the dashboard on the same 2-core machine its replies came > 0.3 s late
# (a new user's trial: 7 ACK timeouts, a port reset and the target lost 5 times in 6 s). A reply
# the service's own loop is late to read is not lost (asyncio runs I/O callbacks before timers).
SIM_LINK_TIMEOUTS = LinkTimeouts(ack_s=1.0, inquiry_s=1.0, cancel_s=1.0)


class DaemonError(RuntimeError):
    """Start-up or run-time failure; the message says what was wrong and what to do."""


async def start_broker(config: DffdConfig, stack: contextlib.AsyncExitStack) -> Any:
    """Start the embedded broker if ``mqtt.url = "embedded"``; return it (None otherwise)."""
    endpoint = config.mqtt.endpoint
    if not endpoint.embedded:
        return None
    from dffd.daemon.broker import BrokerStartError, EmbeddedBroker

    broker = EmbeddedBroker(endpoint.port, endpoint.host)
    try:
        await stack.enter_async_context(broker)
    except BrokerStartError as exc:
        raise DaemonError(str(exc)) from exc
    return broker


def link_timeouts(config: DffdConfig) -> LinkTimeouts | None:
    """The VISCA link's waits for ``config``'s camera (None: the driver's, for hardware)."""
    return SIM_LINK_TIMEOUTS if config.camera.driver == "sim" else None


async def start_camera_transport(
    config: DffdConfig, stack: contextlib.AsyncExitStack, sim_faults: Any
) -> tuple[str, Any, Any]:
    """Return ``(port, sim_server, sim_rig)``: the VISCA port, and the simulator if it is one."""
    cfg = config
    if cfg.camera.driver == "visca":
        assert cfg.camera.port is not None  # validated by the config
        return cfg.camera.port, None, None
    from drivers.sim.device_types import DeviceConfig
    from drivers.sim.rig import build_sim_camera
    from drivers.sim.server import SimCameraServer

    try:
        sim_config = sim_camera_config(cfg)
    except WiringError as exc:
        raise DaemonError(str(exc)) from exc
    rig = build_sim_camera(sim_config, device=DeviceConfig(baud=cfg.camera.baudrate, pace=True))
    transport = cfg.sim.visca_transport
    if transport != "pty":
        from drivers.sim.ip_server import SimUdpServer
        from drivers.sim.net_server import SimTcpServer

        net_cls = SimUdpServer if transport == "udp" else SimTcpServer
        net = await stack.enter_async_context(
            SimThread[SimUdpServer | SimTcpServer](
                lambda: net_cls(rig.device_config, state=rig.state, faults=sim_faults)
            )
        )
        _LOGGER.info("simulated camera on %s", net.url)
        return net.url, net, rig
    # The simulated camera runs on its own event loop in its own thread (dffd.daemon.simthread):
    # a real camera is another device, and the service's loop carries only the service.
    server = await stack.enter_async_context(
        SimThread(lambda: SimCameraServer(rig.device_config, state=rig.state, faults=sim_faults))
    )
    _LOGGER.info("simulated camera on %s", server.path)
    return str(server.path), server, rig


async def open_source(
    config: DffdConfig, sim_rig: Any, stack: contextlib.AsyncExitStack
) -> tuple[FrameSource, float | None, float, Callable[[int], Any] | None]:
    """Return ``(source, exposure_s, focus_speed_counts_per_s, truth_for)`` for the config.

    A network stream is opened here (its frame size is known only then); with ``sim.video =
    "http"`` the simulator's frames are served as MJPEG on a loopback port and read back through
    the same stream source as a network camera's.
    """
    cfg = config
    if cfg.camera.driver == "sim" or cfg.capture.source == "sim":
        if cfg.camera.driver != "sim":
            raise DaemonError(
                "capture.source = 'sim' needs camera.driver = 'sim' (the simulator renders "
                "what its own camera sees); set capture.source = 'v4l2' or 'stream' for a real "
                "camera"
            )
        rig = sim_rig
        exposure_s = rig.config.capture.exposure_s
        focus_speed = rig.device_config.focus_speed_counts_s
        if cfg.sim.video == "direct":
            return rig.source, exposure_s, focus_speed, rig.source.truth_for
        from drivers.sim.video_server import SimVideoServer

        server = SimVideoServer(rig.source)
        await stack.enter_async_context(server)
        _LOGGER.info("simulated camera video on %s", server.url)
        stream = stream_source(cfg, server.url)
        await _start_stream(stream, stack)

        def truth_for(index: int) -> Any:
            # Frame indices of the stream are the reader's: match the truth by exposure time.
            return rig.source.truth_near(stream.exposure_time(index))

        return stream, exposure_s, focus_speed, truth_for
    source = capture_source(cfg)
    if isinstance(source, StreamFrameSource):
        await _start_stream(source, stack)
    profile = profile_for(cfg.camera.model)
    lo, hi = profile.focus_range
    return source, None, (hi - lo) / profile.focus_full_travel_s, None


def camera_model_problem(camera: Camera, configured: str) -> str | None:
    """Why the initialised ``camera`` cannot run under ``camera.model = configured``, or None.

    The driver switches to the profile of a known model the camera identifies as; the
    scheduler's pan/tilt speed tables and range and the focus range were built from the
    configured model. Run on two tables, pan/tilt speeds are chosen on one and converted on the
    other, so the daemon refuses to start instead."""
    wanted = profile_for(configured)
    if camera.profile.key == wanted.key:
        return None
    return (
        f"the camera identifies as the {camera.profile.name} but camera.model is "
        f"{configured!r} (the {wanted.name}): the scheduler's pan/tilt speed tables and range and "
        f"the focus range come from camera.model; set camera.model = {camera.profile.key!r}"
    )


async def initialize_camera(  # noqa: PLR0917 - the daemon's parts the set-up touches
    camera: Camera,
    lens: Lens,
    zoom_counts: int | None,
    scheduler: Scheduler,
    wake: Callable[[], None],
    configured_model: str,
) -> None:
    """Initialise the camera, set the zoom, anchor pan/tilt; re-do it after every reconnect.
    ``configured_model``: ``camera.model``, which a camera identifying as another known model
    contradicts (:func:`camera_model_problem`: a :class:`DaemonError`)."""
    try:
        async with asyncio.timeout(CAMERA_INIT_TIMEOUT_S):
            await camera.initialize()
            problem = camera_model_problem(camera, configured_model)
            if problem is not None:
                raise DaemonError(problem)
            zoom = zoom_counts
            if zoom is None:
                zoom = lens.zoom_counts
            if zoom is not None:
                await camera.zoom_direct(zoom)
            pan, tilt = await camera.pan_tilt_position()
    except (ViscaError, TimeoutError) as exc:
        raise DaemonError(
            f"camera on {camera.link.url} did not initialise: {exc}; check camera.port, "
            "camera.baudrate, the cable and that the camera is powered"
        ) from exc
    scheduler.on_pan_tilt_position(time.monotonic(), pan, tilt)

    async def after_reinit() -> None:
        # The link came back (port reopened, Network Change, power cycle): the camera was
        # re-initialised; its zoom may have reset and the focus and pan/tilt moved.
        now = time.monotonic()
        scheduler.invalidate_focus(now)
        scheduler.on_pan_tilt_failed(now)  # re-anchor the pan/tilt model by inquiry
        wake()
        if zoom is not None:
            try:
                await camera.zoom_direct(zoom)
            except ViscaError as exc:
                _LOGGER.warning("could not restore the zoom after a reconnect: %s", exc)
        _LOGGER.info("camera re-initialised: focus re-learnt by inquiry, zoom restored")

    camera.link.add_reinit_callback(after_reinit)


async def _start_stream(stream: StreamFrameSource, stack: contextlib.AsyncExitStack) -> None:
    try:
        await stream.start()
    except FrameSourceError as exc:
        raise DaemonError(f"capture: {exc}") from exc
    stack.push_async_callback(stream.close)


__all__ = [
    "CAMERA_INIT_TIMEOUT_S",
    "DaemonError",
    "camera_model_problem",
    "initialize_camera",
    "open_source",
    "start_broker",
    "start_camera_transport",
]
