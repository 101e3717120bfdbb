"""``dffd run``: the daemon — camera, capture, scheduler, estimator thread, MQTT, log, systemd.

The asyncio shell (DESIGN §1) only moves bytes, frames and messages; every decision is made by
the pure :class:`~dffd.scheduler.Scheduler` and the estimation core. Layout at run time:

* tasks under one ``asyncio.TaskGroup``: **capture** (frame source → scheduler tag → estimator
  queue), **scheduler** (wakes on events and on the scheduler's own wake-up time, dispatches its
  actions), **focus** and **pan/tilt** workers (one action in flight each, on the camera's two
  VISCA sockets at once), **results** (estimator output → MQTT + JSONL log + scheduler
  feedback), **status** (retained status, console, sd_notify watchdog), and the MQTT
  **publisher**;
* ONE estimator thread running the core behind ONE bounded frame queue (drop-oldest, counted:
  capture never blocks); results come back through ``loop.call_soon_threadsafe`` into a bounded
  queue (drop-oldest, counted). Commands that change the core (acquire, release, known size)
  are applied by that thread between frames, so the core is never touched concurrently.

Without ``--config`` (or with ``camera.driver = "sim"``) the camera is the simulator: its VISCA
device on a real pty (:class:`~drivers.sim.server.SimCameraServer`), its renderer as the frame
source, ground truth on ``…/sim/truth``; ``mqtt.url = "embedded"`` starts the embedded amqtt
broker on 127.0.0.1. The world is ``sim.scenario``'s ``[target]`` and ``[trajectory]`` tables (a
world shipped in ``drivers/sim/data/worlds/``, or a file path) applied to the
simulated camera's own config types (``drivers.sim.config``), ``sim.start_phase_deg`` overriding
the start phase (the default demo starts the circle at its far point). With a config naming a
serial port, a video device (``[capture]`` → :class:`drivers.capture.OpenCVFrameSource`) and a
broker it is the lab service.

Acquisition (the same live and on the simulator): the lens goes to
``scheduler.initial_focus_depth_m``; while the core is not tracking only frames exposed at a
stationary focus reach it (a contour started on a frame blurred by focus travel is lost within a
few frames); bursts start after ``acquire_stable_frames`` frames with a contour; pan/tilt follows
with velocity feed-forward from the first two centroids; after a loss the head searches along the
target's predicted path, then returns to where it was last seen, while the core keeps searching
(see :mod:`dffd.scheduler`).

Shutdown (SIGTERM/SIGINT): stop pan/tilt, publish the retained ``offline`` status, flush the
JSONL log, exit 0 — all within :data:`SHUTDOWN_TIMEOUT_S`. sd_notify READY is sent once the
camera is initialised and frames flow; WATCHDOG pings come from the status task only while
frames flow.

Exit codes: 0 clean stop, 1 runtime failure (camera, broker, capture, log), 2 configuration.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import os
import signal
import sys
import threading
import time
import tomllib
from collections import deque
from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel, ValidationError

from dffd import __version__
from dffd.config import ConfigError, DffdConfig, load_config, problems
from dffd.core.lens import Lens, LensError
from dffd.core.pipeline import Estimate as CoreEstimate
from dffd.core.pipeline import Measurement as CoreMeasurement
from dffd.core.pipeline import Pipeline
from dffd.core.types import FrameTag
from dffd.daemon.actuators import Actuators
from dffd.daemon.console import Console, ConsoleSnapshot
from dffd.daemon.jsonlog import JsonlLog, JsonlLogError
from dffd.daemon.notify import Notifier
from dffd.exitcodes import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from dffd.mqtt import models
from dffd.mqtt.publisher import CommandRejected, Publisher, PublisherSettings
from dffd.mqtt.topics import Topics
from dffd.scheduler import Action, Scheduler, SchedulerConfig, depth_rate_limit
from dffd.step import CoreStep, StepResult
from dffd.web.interface import Snapshot
from dffd.web.listen import WebConfigError
from dffd.wiring import build_core, scheduler_config
from drivers.frames import Frame, FrameSource, FrameSourceError
from drivers.visca.camera import Camera, profile_for
from drivers.visca.errors import ViscaError
from drivers.visca.link import ViscaLink

if TYPE_CHECKING:
    from dffd.daemon.dashboard import Dashboard
    from dffd.web.server import WebSettings

_LOGGER = logging.getLogger(__name__)


# -- named timings and bounds -----------------------------------------------------------------
# Whole shutdown (stop pan/tilt, offline status, log flush, thread join): systemd's default
# TimeoutStopSec is 90 s; 10 s keeps a restart quick and covers a broker that does not answer.
SHUTDOWN_TIMEOUT_S = 10.0
# Pan/tilt stop at shutdown: one command and its Completion (~2 fields) with retries.
PAN_TILT_STOP_TIMEOUT_S = 2.0
# Camera initialisation: Address Set, IF_Clear, power (the D100 takes ~10 s from standby), zoom.
CAMERA_INIT_TIMEOUT_S = 30.0
# A frame must arrive within this time (30 fps → 33 ms; a USB grabber may stall ~1 s on
# re-negotiation) before capture is reported stalled (it then keeps waiting).
FRAME_TIMEOUT_S = 2.0
# Frames flow if the last one is younger than this (watchdog pings and READY depend on it).
FRAMES_FLOWING_S = 1.0
# Status (retained), console and watchdog period. Also the rate window's granularity.
STATUS_PERIOD_S = 1.0
# Window over which achieved rates are computed.
RATE_WINDOW_S = 5.0
# The scheduler task sleeps at most this long without an event (guards against a lost wake-up).
# Shortest wait when the scheduler asks to be woken in the past but has nothing to do: far
# below its timing resolution (one video field, 16.7 ms), so it costs no accuracy, yet it keeps
# a past wake-up from becoming a busy loop.
SCHEDULER_MIN_WAIT_S = 0.001
SCHEDULER_IDLE_S = 0.5
# Bounded queues (DESIGN §8: no unbounded queue anywhere).
FRAME_QUEUE_MAX = 4  # estimator input: a few frames of slack at 30 fps, then drop the oldest
RESULT_QUEUE_MAX = 64  # estimator output waiting for the event loop
COMMAND_QUEUE_MAX = 16  # core commands waiting for the estimator thread
# Estimator thread: waits for frames in slices so it notices a stop request.
ESTIMATOR_POLL_S = 0.2
ESTIMATOR_JOIN_TIMEOUT_S = 2.0
# Core commands wait at most this long for the estimator thread to apply them.
CORE_COMMAND_TIMEOUT_S = 2.0
# Nominal bracket spacing (counts) for the rate limit until the core plans a burst.
DEFAULT_SPACING_COUNTS = 300
# Frames waiting between the capture thread and the loop (drop-oldest beyond): the estimator
# wants the newest frame; two absorb one slow loop iteration.
CAPTURE_QUEUE_FRAMES = 2


_M = TypeVar("_M", bound=BaseModel)


class DaemonError(RuntimeError):
    """Start-up or run-time failure; the message says what was wrong and what to do."""


# -- CLI ----------------------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    """Run until SIGTERM/SIGINT (or ``--duration``); return the exit code."""
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"dffd run: {exc}", file=sys.stderr)
        return EXIT_USAGE
    missing = problems(config, devices=True)
    if missing:
        print("dffd run: " + "; ".join(missing), file=sys.stderr)
        return EXIT_USAGE
    logging.getLogger("dffd").setLevel(config.log.level)
    live = not args.no_console and sys.stdout.isatty()
    if not live and not logging.getLogger().isEnabledFor(logging.INFO):
        # Without a TTY the status lines are the console; make sure they are visible.
        logging.getLogger("dffd.daemon.console").setLevel(logging.INFO)
        logging.getLogger().setLevel(logging.INFO)
    from drivers.sim.faults import Faults, FaultSpecError

    try:
        faults = Faults(args.sim_faults) if args.sim_faults else None
    except FaultSpecError as exc:
        print(f"dffd run: --sim-faults: {exc}", file=sys.stderr)
        return EXIT_USAGE
    daemon = Daemon(config, live_console=live, duration_s=args.duration, sim_faults=faults)
    try:
        return asyncio.run(daemon.main())
    except KeyboardInterrupt:
        return EXIT_OK


# -- the estimator thread ------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class _Work:
    frame: Frame
    tag: FrameTag


@dataclass(frozen=True, slots=True)
class EstimatorResult:
    """One processed frame, handed back to the event loop."""

    step: StepResult
    cpu_s: float  # estimator thread CPU time spent on the frame
    frame: Frame  # the processed frame (the dashboard draws on the newest one)

    @property
    def frame_index(self) -> int:
        """Index of the processed frame."""
        return self.step.frame_index


CoreCommand = Callable[[Pipeline], dict[str, Any] | None]


class EstimatorThread:
    """The core in one dedicated thread behind one bounded drop-oldest queue."""

    def __init__(
        self,
        core: CoreStep,
        deliver: Callable[[EstimatorResult], object],
        queue_max: int = FRAME_QUEUE_MAX,
    ) -> None:
        self.core = core
        self._deliver = deliver
        self._frames: deque[_Work] = deque(maxlen=queue_max)
        self._commands: deque[tuple[CoreCommand, Future[dict[str, Any] | None]]] = deque(
            maxlen=COMMAND_QUEUE_MAX
        )
        self._cond = threading.Condition()
        self._stop = False
        self.dropped = 0
        self.processed = 0
        self._thread = threading.Thread(target=self._run, name="dffd-estimator", daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def submit(self, frame: Frame, tag: FrameTag) -> None:
        """Queue a frame (never blocks; drops the oldest queued frame when full)."""
        with self._cond:
            if len(self._frames) == self._frames.maxlen:
                self.dropped += 1
            self._frames.append(_Work(frame, tag))
            self._cond.notify()

    def call(self, command: CoreCommand) -> Future[dict[str, Any] | None]:
        """Run ``command(pipeline)`` in the estimator thread before the next frame."""
        future: Future[dict[str, Any] | None] = Future()
        with self._cond:
            if len(self._commands) == self._commands.maxlen:
                future.set_exception(CommandRejected("too many pending commands; retry"))
                return future
            self._commands.append((command, future))
            self._cond.notify()
        return future

    def stop(self, timeout_s: float = ESTIMATOR_JOIN_TIMEOUT_S) -> bool:
        """Ask the thread to finish and join it; True if it did in time."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not (self._stop or self._frames or self._commands):
                    self._cond.wait(ESTIMATOR_POLL_S)
                if self._stop:
                    return
                commands = list(self._commands)
                self._commands.clear()
                work = self._frames.popleft() if self._frames else None
            for command, future in commands:
                try:
                    future.set_result(command(self.core.pipeline))
                except Exception as exc:  # noqa: BLE001 - a bad command is answered, never fatal
                    future.set_exception(exc)
            if work is not None:
                try:
                    self._deliver(self._process(work))
                except Exception:  # the core must not kill the service on one bad frame
                    _LOGGER.exception("estimator failed on frame %d", work.frame.index)

    def _process(self, work: _Work) -> EstimatorResult:
        c0 = time.thread_time()
        step = self.core.step(work.frame, work.tag)
        self.processed += 1
        return EstimatorResult(step, time.thread_time() - c0, work.frame)


# -- rates ----------------------------------------------------------------------------------------
class RateMeter:
    """Events per second over a sliding window (bounded memory)."""

    def __init__(self, window_s: float = RATE_WINDOW_S, max_events: int = 4096) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque(maxlen=max_events)
        self.count = 0

    def add(self, t: float) -> None:
        """Record one event at ``t``."""
        self._times.append(t)
        self.count += 1

    def rate(self, now: float) -> float:
        """Events per second over the window ending at ``now``."""
        while self._times and now - self._times[0] > self.window_s:
            self._times.popleft()
        if len(self._times) < 2:
            return 0.0
        span = max(now - self._times[0], self._times[-1] - self._times[0])
        return (len(self._times) - 1) / span if span > 0 else 0.0


# -- the daemon -----------------------------------------------------------------------------------
@dataclass
class _Parts:
    """Everything started, for orderly shutdown."""

    broker: Any = None
    sim_server: Any = None
    link: ViscaLink | None = None
    source: FrameSource | None = None
    log: JsonlLog | None = None
    estimator: EstimatorThread | None = None
    truth_for: Callable[[int], Any] | None = None
    exits: list[Callable[[], Awaitable[None]]] = field(default_factory=list)


class Daemon:
    """One dffd service instance; :meth:`main` runs it to completion."""

    def __init__(
        self,
        config: DffdConfig,
        *,
        live_console: bool = False,
        duration_s: float | None = None,
        sim_faults: Any = None,
    ) -> None:
        self.config = config
        self.sim_faults = sim_faults
        self.duration_s = duration_s
        self.console = Console(live=live_console)
        self.notifier = Notifier()
        self.topics = Topics(config.mqtt.topic_prefix, config.camera.name)
        self.stop_requested = asyncio.Event()
        self._parts = _Parts()
        self._wake = asyncio.Event()
        self._results: asyncio.Queue[EstimatorResult] = asyncio.Queue(RESULT_QUEUE_MAX)
        self.results_dropped = 0
        self.payloads_skipped = 0  # core outputs that did not fit the MQTT schema
        self.frames = RateMeter()
        self.estimates = RateMeter()
        self.measurements = RateMeter()
        self.bursts_accepted = 0
        self.bursts_rejected = 0
        self._estimate_seq = 0
        self._measurement_seq = 0
        self._last_frame_mono: float | None = None
        self._ready_sent = False
        self._state = "acquiring"
        self._message: str | None = None  # what the operator should know (status, dashboard)
        self._last_estimate_mono: float | None = None  # None: none since start or release
        self._last_depth: dict[str, float | None] = {}
        self._last_truth_z: float | None = None
        self._last_size: float | None = None
        self._spacing = DEFAULT_SPACING_COUNTS
        self._t_start = time.monotonic()
        self.camera: Camera | None = None
        self.scheduler: Scheduler | None = None
        self.publisher: Publisher | None = None
        self._sched_config: SchedulerConfig | None = None
        self._zoom: int | None = None
        self.dashboard: Dashboard | None = None
        self._web: WebSettings | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    async def main(self) -> int:
        """Start everything, run until stopped, shut down; return the exit code."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.request_stop)
        code = EXIT_OK
        try:
            with self.console:
                await self._run()
        except* DaemonError as group:
            for error in group.exceptions:
                _LOGGER.error("%s", error)
            code = EXIT_FAILURE
        except* (ViscaError, FrameSourceError, JsonlLogError, OSError) as failures:
            for failure in failures.exceptions:
                _LOGGER.error("dffd stopped: %s", failure)
            code = EXIT_FAILURE
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
        return code

    def request_stop(self) -> None:
        """Begin an orderly shutdown (signal handler; idempotent)."""
        if not self.stop_requested.is_set():
            _LOGGER.info("stop requested: stopping pan/tilt, publishing offline, flushing")
            self.notifier.stopping("shutting down")
            # The bound on shutdown: whatever hangs (a dead broker, a stuck port), exit anyway.
            asyncio.get_running_loop().call_later(SHUTDOWN_TIMEOUT_S, _force_exit)
        self.stop_requested.set()
        self._wake.set()

    async def _run(self) -> None:
        cfg = self.config
        try:
            lens = Lens.from_toml(cfg.lens.file)
        except LensError as exc:
            raise DaemonError(f"lens.file: {exc}") from exc
        # Imported here: aiohttp and prometheus-client stay off the path of `dffd run --help`.
        from dffd.daemon import dashboard

        try:
            self._web = dashboard.settings_for(cfg.web)
        except WebConfigError as exc:
            raise DaemonError(str(exc)) from exc
        core = build_core(cfg, lens)
        self.dashboard = dashboard.Dashboard(
            self.dashboard_snapshot,
            self._execute,
            normal_half_px=float(core.pipeline.config.search_px),
            counts_range=lens.counts_range,
        )
        try:
            async with contextlib.AsyncExitStack() as stack:
                await self._start_broker(stack)
                port = await self._start_camera_transport(stack)
                source, exposure_s, focus_speed = await self._start_source(stack, lens)
                self._sched_config = scheduler_config(
                    self.config,
                    fps=source.fps,
                    exposure_s=exposure_s,
                    focus_speed_counts_per_s=focus_speed,
                    focal_length_mm=lens.focal_length_mm,
                    pixel_pitch_mm=lens.pixel_pitch_mm,
                    frame_size=source.frame_size,
                )
                self.scheduler = Scheduler(self._sched_config)
                self.scheduler.set_track_focus(
                    lens.counts_for_depth(cfg.scheduler.initial_focus_depth_m)
                )
                log = JsonlLog(
                    cfg.log.dir, max_bytes=cfg.log.max_bytes, backup_count=cfg.log.backup_count
                )
                log.start()
                self._parts.log = log
                stack.push_async_callback(self._close_log)
                self.publisher = Publisher(
                    PublisherSettings.from_config(cfg.mqtt),
                    self.topics,
                    on_command=self._on_command,
                )
                loop = asyncio.get_running_loop()
                estimator = EstimatorThread(
                    core, lambda r: loop.call_soon_threadsafe(self._on_result, r)
                )
                estimator.start()
                self._parts.estimator = estimator
                stack.callback(estimator.stop)
                await self._serve(port, source, lens)
        except TimeoutError as exc:
            raise DaemonError(f"start-up timed out: {exc or 'no answer'}") from exc

    async def _serve(self, port: str, source: FrameSource, lens: Lens) -> None:
        cfg = self.config
        assert self.publisher is not None
        publisher = self.publisher
        link = ViscaLink(port, cfg.camera.baudrate)
        self._parts.link = link
        async with asyncio.TaskGroup() as group:
            pub_task = group.create_task(publisher.run(), name="mqtt")
            web_task = None
            if self._web is not None and self.dashboard is not None:
                from dffd.daemon.dashboard import serve

                web_task = group.create_task(serve(self._web, self.dashboard), name="web")
            try:
                async with link:
                    camera = Camera(link, cfg.camera.address, profile_for(cfg.camera.model))
                    await self._initialize_camera(camera, lens)
                    self.camera = camera
                    assert self.scheduler is not None
                    actuators = Actuators(camera, self.scheduler, self._wake.set)
                    await source.start()
                    tasks = [
                        group.create_task(self._capture_loop(source), name="capture"),
                        group.create_task(
                            self._scheduler_loop(actuators.dispatch), name="scheduler"
                        ),
                        group.create_task(actuators.run_focus(), name="focus"),
                        group.create_task(actuators.run_pan_tilt(), name="pan-tilt"),
                        group.create_task(self._results_loop(), name="results"),
                        group.create_task(self._status_loop(), name="status"),
                    ]
                    await self._wait_for_stop()
                    for task in tasks:
                        task.cancel()
                    await asyncio.gather(*tasks, return_exceptions=True)
                    await self._shutdown_camera(camera)
            finally:
                if web_task is not None:
                    await _cancel(web_task)
                await self._shutdown_publisher(publisher, pub_task)

    async def _wait_for_stop(self) -> None:
        if self.duration_s is None:
            await self.stop_requested.wait()
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.duration_s):
                await self.stop_requested.wait()
        self.request_stop()

    async def _shutdown_camera(self, camera: Camera) -> None:
        try:
            async with asyncio.timeout(PAN_TILT_STOP_TIMEOUT_S):
                await camera.pan_tilt_stop()
            _LOGGER.info("pan/tilt stopped")
        except (ViscaError, TimeoutError) as exc:
            _LOGGER.warning("could not stop pan/tilt at shutdown: %s", exc)
        await self._source_close()

    async def _source_close(self) -> None:
        source = self._parts.source
        if source is not None:
            with contextlib.suppress(FrameSourceError, TimeoutError):
                async with asyncio.timeout(PAN_TILT_STOP_TIMEOUT_S):
                    await source.close()

    async def _shutdown_publisher(self, publisher: Publisher, task: asyncio.Task[None]) -> None:
        publisher.publish(publisher.status_payload("offline", "stopped"))
        await publisher.stop()
        if not task.done():
            task.cancel()

    async def _close_log(self) -> None:
        log = self._parts.log
        if log is not None and not await log.aclose():
            _LOGGER.error("JSONL log did not flush in time; the last records may be missing")

    # -- start-up pieces ------------------------------------------------------------------------
    async def _start_broker(self, stack: contextlib.AsyncExitStack) -> None:
        endpoint = self.config.mqtt.endpoint
        if not endpoint.embedded:
            return
        from dffd.daemon.broker import BrokerStartError, EmbeddedBroker

        broker = EmbeddedBroker(endpoint.port, endpoint.host)
        try:
            await stack.enter_async_context(broker)
        except BrokerStartError as exc:
            raise DaemonError(str(exc)) from exc
        self._parts.broker = broker

    async def _start_camera_transport(self, stack: contextlib.AsyncExitStack) -> str:
        cfg = self.config
        if cfg.camera.driver == "visca":
            assert cfg.camera.port is not None  # validated by the config
            return cfg.camera.port
        from drivers.sim.device import DeviceConfig
        from drivers.sim.rig import build_sim_camera
        from drivers.sim.server import SimCameraServer

        rig = build_sim_camera(
            self._sim_camera_config(), device=DeviceConfig(baud=cfg.camera.baudrate, pace=True)
        )
        transport = cfg.sim.visca_transport
        if transport != "pty":
            from drivers.sim.ip_server import SimUdpServer
            from drivers.sim.net_server import SimTcpServer

            net_cls = SimUdpServer if transport == "udp" else SimTcpServer
            net = net_cls(rig.device_config, state=rig.state, faults=self.sim_faults)
            await stack.enter_async_context(net)
            self._parts.sim_server = net
            self._sim_rig = rig
            _LOGGER.info("simulated camera on %s", net.url)
            return net.url
        server = SimCameraServer(rig.device_config, state=rig.state, faults=self.sim_faults)
        await stack.enter_async_context(server)
        self._parts.sim_server = server
        self._sim_rig = rig
        _LOGGER.info("simulated camera on %s", server.path)
        return str(server.path)

    def _sim_camera_config(self) -> Any:
        """The simulated camera of ``sim.camera_config`` looking at ``sim.scenario``'s world."""
        from drivers.sim.config import SimConfigError, load_sim_camera_config, with_overrides
        from drivers.sim.resources import reference_camera_file

        cfg = self.config
        path = cfg.sim.camera_config or reference_camera_file()
        target, trajectory = _scenario_world(cfg.sim.scenario_file)
        trajectory = {**trajectory, "seed": cfg.sim.seed}
        if cfg.sim.start_phase_deg is not None:
            trajectory["phase_deg"] = cfg.sim.start_phase_deg
        try:
            base = load_sim_camera_config(path)
            overrides: dict[str, Any] = {
                "seed": cfg.sim.seed,
                "world.target": target,
                "world.trajectory": trajectory,
                "capture.fps": cfg.capture.fps,
            }
            return with_overrides(base, overrides)
        except SimConfigError as exc:
            raise DaemonError(f"sim.camera_config / sim.scenario: {exc}") from exc

    async def _start_source(
        self, stack: contextlib.AsyncExitStack, lens: Lens
    ) -> tuple[FrameSource, float | None, float]:
        cfg = self.config
        if cfg.camera.driver == "sim" or cfg.capture.source == "sim":
            if cfg.camera.driver != "sim":
                raise DaemonError(
                    "capture.source = 'sim' needs camera.driver = 'sim' (the simulator renders "
                    "what its own camera sees); set capture.source = 'v4l2' for a real camera"
                )
            rig = self._sim_rig
            self._parts.source = rig.source
            self._parts.truth_for = rig.source.truth_for
            stack.push_async_callback(self._source_close)
            return rig.source, rig.config.capture.exposure_s, rig.device_config.focus_speed_counts_s
        source = _open_capture(cfg)
        self._parts.source = source
        stack.push_async_callback(self._source_close)
        profile = profile_for(cfg.camera.model)
        lo, hi = profile.focus_range
        return source, None, (hi - lo) / profile.focus_full_travel_s

    async def _initialize_camera(self, camera: Camera, lens: Lens) -> None:
        try:
            async with asyncio.timeout(CAMERA_INIT_TIMEOUT_S):
                await camera.initialize()
                zoom = self.config.lens.zoom_counts
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
        assert self.scheduler is not None
        self.scheduler.on_pan_tilt_position(time.monotonic(), pan, tilt)
        self._zoom = zoom

        async def after_reinit() -> None:
            # The link came back (port reopened, Network Change, power cycle): the camera was
            # re-initialised; its zoom may have reset and the focus and pan/tilt moved.
            sched = self.scheduler
            assert sched is not None
            now = time.monotonic()
            sched.invalidate_focus(now)
            sched.on_pan_tilt_failed(now)  # re-anchor the pan/tilt model by inquiry
            self._wake.set()
            if self._zoom is not None:
                try:
                    await camera.zoom_direct(self._zoom)
                except ViscaError as exc:
                    _LOGGER.warning("could not restore the zoom after a reconnect: %s", exc)
            _LOGGER.info("camera re-initialised: focus re-learnt by inquiry, zoom restored")

        camera.link.add_reinit_callback(after_reinit)

    # -- tasks ---------------------------------------------------------------------------------
    async def _capture_loop(self, source: FrameSource) -> None:
        sched = self.scheduler
        estimator = self._parts.estimator
        assert sched is not None
        assert estimator is not None
        stalled = False
        while True:
            try:
                async with asyncio.timeout(FRAME_TIMEOUT_S):
                    frame = await source.next_frame()
            except TimeoutError:
                (_LOGGER.debug if stalled else _LOGGER.warning)(
                    "no frame for %.1f s; capture stalled (watchdog pings paused)",
                    FRAME_TIMEOUT_S,
                )
                stalled = True
                continue
            stalled = False
            now = time.monotonic()
            self._last_frame_mono = now
            self.frames.add(now)
            tag = sched.on_frame(frame.index, frame.t)
            estimator.submit(frame, tag)
            self._wake.set()
            self._publish_truth(frame)

    def _publish_truth(self, frame: Frame) -> None:
        truth_for = self._parts.truth_for
        if truth_for is None or not self.config.sim.publish_truth:
            return
        truth = truth_for(frame.index)
        if truth is None:
            return
        self._last_truth_z = float(truth.z_m)
        assert self.publisher is not None
        self.publisher.publish(
            models.Truth(
                t=models.wall_time(),
                t_mono=frame.t,
                z_m=float(truth.z_m),
                position_m=_vec(truth.position_world_m) or (0.0, 0.0, 0.0),
                size_m=float(truth.size_m) if truth.size_m > 0 else None,
            )
        )

    async def _scheduler_loop(self, dispatch: Callable[[Action], object]) -> None:
        sched = self.scheduler
        assert sched is not None
        while True:
            now = time.monotonic()
            actions = sched.next_actions(now)
            for action in actions:
                _LOGGER.debug("action at %.4f: %r", now, action)
                dispatch(action)
            wake = sched.next_wakeup()
            delay = SCHEDULER_IDLE_S if wake is None else min(SCHEDULER_IDLE_S, wake - now)
            self._wake.clear()
            if delay <= 0 and actions:
                # A wake-up already due: yield anyway, or a scheduler that keeps one in the past
                # would starve the loop (and the Completion it may be waiting for).
                await asyncio.sleep(0)
                continue
            # A due wake-up that produced nothing would otherwise spin: wait at least a little.
            delay = max(delay, SCHEDULER_MIN_WAIT_S)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay):
                    await self._wake.wait()

    def _on_result(self, result: EstimatorResult) -> None:
        """On the loop (via call_soon_threadsafe): queue a result, dropping the oldest."""
        if self._results.full():
            self._results.get_nowait()
            self.results_dropped += 1
        self._results.put_nowait(result)

    async def _results_loop(self) -> None:
        sched = self.scheduler
        log = self._parts.log
        publisher = self.publisher
        assert sched is not None
        assert log is not None
        assert publisher is not None
        while True:
            result = await self._results.get()
            now = time.monotonic()
            out = result.step.output
            self._state = out.state
            if out.state != "idle":
                self._message = None
            if self.dashboard is not None:
                self.dashboard.on_result(result.frame, result.step, result.cpu_s)
            if out.measurement is not None:
                if out.measurement.accepted:
                    self.bursts_accepted += 1
                else:
                    self.bursts_rejected += 1
                self.measurements.add(now)
                payload_m = self._payload_or_none(self._measurement_payload, out.measurement)
                if payload_m is not None:
                    log.append("measurement", payload_m)
                    publisher.publish(payload_m)
                    if self.dashboard is not None:
                        self.dashboard.on_measurement(payload_m)
            payload_e = None
            if out.estimate is not None:
                payload_e = self._payload_or_none(self._estimate_payload, out.estimate)
            if payload_e is not None:
                self.estimates.add(now)
                self._last_depth = dict(payload_e.depth_m.model_dump())
                self._last_size = payload_e.size_m
                log.append("estimate", payload_e)
                publisher.publish(payload_e)
                self._last_estimate_mono = now
                if self.dashboard is not None:
                    self.dashboard.on_estimate(payload_e, self._truth_z(result.frame_index), now)
            feedback = result.step.feedback
            if feedback.plan is not None:
                self._spacing = max(1, (max(feedback.plan) - min(feedback.plan)) // 2)
            feedback.apply(sched)
            self._wake.set()

    async def _status_loop(self) -> None:
        publisher = self.publisher
        assert publisher is not None
        while True:
            now = time.monotonic()
            flowing = self._frames_flowing(now)
            if flowing and not self._ready_sent:
                self.notifier.ready("camera initialised, frames flowing")
                self._ready_sent = True
                _LOGGER.info("ready: camera initialised and frames flowing")
            if flowing:
                self.notifier.watchdog()
            # A status that cannot be built must not end the status task (and with it the
            # watchdog pings): skip that period, counted like any other unpublishable payload.
            status = self._payload_or_none(self.status_payload, now)
            if status is not None:
                publisher.publish(status)
                self.console.update(self._snapshot(now, status))
            await asyncio.sleep(STATUS_PERIOD_S)

    # -- commands ------------------------------------------------------------------------------
    async def _on_command(self, command: models.Command) -> dict[str, Any] | None:
        sched = self.scheduler
        estimator = self._parts.estimator
        if sched is None or estimator is None:
            raise CommandRejected("the daemon is still starting; retry in a few seconds")
        if isinstance(command, models.Acquire) and command.roi is None:
            await self._core(lambda p: p.acquire_auto())
            self._set_roi(None)
            self._state, self._message = "acquiring", None
            _LOGGER.info("acquire: searching the whole frame for the target (automatic detection)")
            return {"roi": None}
        if isinstance(command, models.Acquire):
            assert command.roi is not None
            x, y, w, h = command.roi
            fw, fh = sched.config.frame_size
            if x + w > fw or y + h > fh:
                raise CommandRejected(
                    f"roi {list(command.roi)} extends beyond the {fw}x{fh} frame; "
                    "give [x, y, w, h] inside the image"
                )
            await self._core(lambda p: p.acquire_roi(x, y, w, h))
            self._set_roi((x, y, w, h))
            self._state, self._message = "acquiring", None
            _LOGGER.info("acquire: target inside roi [%d, %d, %d, %d]", x, y, w, h)
            return {"roi": [x, y, w, h]}
        if isinstance(command, models.Release):
            await self._core(lambda p: p.release())
            sched.cancel_bursts()
            sched.stop_pan_tilt()
            self._wake.set()
            self._drop_pending_results()
            self._set_roi(None)
            self._state = "idle"
            self._message = "released by command: no depths until an acquire command"
            self._last_estimate_mono = None
            self._last_depth = {}
            _LOGGER.info("released by command: idle, no depths published until 'acquire'")
            return None
        if isinstance(command, models.SetKnownSize):
            size = command.size_m
            await self._core(lambda p: p.set_known_size(size))
            return {"size_m": size}
        if isinstance(command, models.Home):
            camera = self.camera
            if camera is None:
                raise CommandRejected("camera not initialised yet; retry")
            sched.stop_pan_tilt()
            self._wake.set()
            try:
                await camera.home()
            except ViscaError as exc:
                raise CommandRejected(f"home failed: {exc}") from exc
            sched.on_pan_tilt_failed(time.monotonic())  # re-anchor the model by inquiry
            return None
        if isinstance(command, models.SetBurstPolicy):
            cfg = sched.config
            every = command.every_n_frames or cfg.burst_every_frames
            sigma = None
            if command.policy == "sigma":
                sigma = command.sigma_threshold_m or self.config.scheduler.sigma_threshold_m
            sched.set_policy(every, sigma)
            self._wake.set()
            return {"policy": command.policy, "every_n_frames": every, "sigma_threshold_m": sigma}
        raise CommandRejected(f"unsupported command {command!r}")

    async def _core(self, command: Callable[[Pipeline], object]) -> None:
        estimator = self._parts.estimator
        assert estimator is not None

        def wrapped(pipeline: Pipeline) -> dict[str, Any] | None:
            command(pipeline)
            return None

        future = estimator.call(wrapped)
        try:
            async with asyncio.timeout(CORE_COMMAND_TIMEOUT_S):
                await asyncio.wrap_future(future)
        except ValueError as exc:
            raise CommandRejected(str(exc)) from exc
        except TimeoutError as exc:
            raise CommandRejected(
                f"the estimator did not apply the command within {CORE_COMMAND_TIMEOUT_S:.0f} s "
                "(it is behind on frames); retry"
            ) from exc

    # -- payloads --------------------------------------------------------------------------------
    def _estimate_payload(self, est: CoreEstimate) -> models.Estimate:
        self._estimate_seq += 1
        d = est.depth_m
        depth = models.DepthByEstimator(
            measured=_fin(d.get("measured")),
            cf1=_fin(d.get("cf1")),
            cf2=_fin(d.get("cf2")),
            lpv=_fin(d.get("lpv")),
            kf=_fin(d.get("kf")),
        )
        best = est.best if est.best in ("lpv", "kf", "cf2", "cf1") else self.config.estimators.best
        return models.Estimate(
            seq=self._estimate_seq,
            t=models.wall_time(),
            t_mono=est.t,
            state=est.state,
            depth_m=depth,
            best=best,
            z_m=_fin(est.z_m),
            sigma_m=_nonneg(est.sigma_m),
            beta_m_s=_fin(est.beta_m_s),
            size_m=_nonneg(est.size_m),
            r_px=_nonneg(est.r_px),
            rho_per_s=_fin(est.rho),
            position_m=_vec(est.position_world_m),
            velocity_m_s=_vec(est.velocity_world_m_s),
            pan_deg=_fin(est.pan_deg) or 0.0,
            tilt_deg=_fin(est.tilt_deg) or 0.0,
            focus_counts=est.focus_counts if est.focus_counts and est.focus_counts >= 0 else None,
        )

    def _payload_or_none(self, build: Callable[[Any], _M], item: Any) -> _M | None:
        """A payload, or None (logged, counted) when the core's output does not fit the schema.

        One odd result must never stop the service: e.g. the core reports a burst cut short by
        a link fault with fewer than the three frames the ``…/measurement`` schema requires.
        """
        try:
            return build(item)
        except ValidationError as exc:
            self.payloads_skipped += 1
            level = logging.DEBUG if self.payloads_skipped > 1 else logging.WARNING
            _LOGGER.log(level, "not published (%d so far): %s", self.payloads_skipped, exc)
            return None

    def _measurement_payload(self, m: CoreMeasurement) -> models.Measurement:
        self._measurement_seq += 1
        costs = [max(0.0, _fin(c) or 0.0) for c in m.costs]
        return models.Measurement(
            seq=self._measurement_seq,
            burst=max(0, m.burst_id),
            t=models.wall_time(),
            t_mono=m.t,
            focus_counts=[max(0, int(c)) for c in m.focus_counts],
            v_mm=[_fin(v) or 0.0 for v in m.v_mm],
            costs=costs,
            fit=models.Fit(
                alpha=_fin(m.alpha),
                v_mm=_fin(m.v_hat_mm),
                residual=_nonneg(m.residual),
                accepted=m.accepted,
                reason=m.reason or None,
            ),
            z_m=_fin(m.z_m),
            sigma_m=_nonneg(m.sigma_m),
        )

    def status_payload(self, now: float) -> models.Status:
        """The retained ``…/status`` payload now."""
        publisher = self.publisher
        assert publisher is not None
        stats = publisher.stats()
        limit = self.depth_limit_hz()
        return models.Status(
            availability="online",
            t=models.wall_time(),
            t_mono=now,
            state=self._state,  # type: ignore[arg-type]
            camera=self.config.camera.name,
            last_estimate_age_s=self._estimate_age(now),
            message=self._message,
            rates=models.Rates(
                frame_hz=self.frames.rate(now),
                estimate_hz=self.estimates.rate(now),
                depth_hz=self.measurements.rate(now),
                depth_limit_hz=_nonneg(limit),
            ),
            link=self._link_health(now),
            mqtt=publisher.health(),
            drops=models.Drops(
                frames=self.frames_dropped(),
                publish_queue=stats.queue_dropped,
                backlog=stats.backlog_dropped,
                log=self._parts.log.stats().dropped if self._parts.log else 0,
            ),
            version=__version__,
        )

    def dashboard_snapshot(self) -> Snapshot | None:
        """The dashboard's view now (None until the publisher exists)."""
        if self.publisher is None:
            return None
        now = time.monotonic()
        source = self._parts.source
        return Snapshot(
            status=self.status_payload(now),
            last_estimate_age_s=self._estimate_age(now),
            bursts_accepted=self.bursts_accepted,
            bursts_rejected=self.bursts_rejected,
            frame_size=source.frame_size if source is not None else None,
            message=self._message,
        )

    async def _execute(self, payload: bytes) -> models.CommandReply:
        """A dashboard command, through the MQTT command path (same validation and reply)."""
        if self.publisher is None:
            return models.CommandReply(
                id=None, ok=False, error="the daemon is still starting; retry",
                t=models.wall_time(),
            )  # fmt: skip
        return await self.publisher.execute(payload)

    def _estimate_age(self, now: float) -> float | None:
        last = self._last_estimate_mono
        return None if last is None else max(0.0, now - last)

    def _truth_z(self, frame_index: int) -> float | None:
        truth_for = self._parts.truth_for
        truth = truth_for(frame_index) if truth_for is not None else None
        return None if truth is None else float(truth.z_m)

    def _set_roi(self, roi: tuple[int, int, int, int] | None) -> None:
        if self.dashboard is not None:
            self.dashboard.roi = roi

    def _drop_pending_results(self) -> None:
        """Forget results of frames processed before a release: nothing stale is published."""
        while not self._results.empty():
            self._results.get_nowait()

    def depth_limit_hz(self) -> float | None:
        """Theoretical depth-measurement rate of this configuration at the current spacing."""
        if self._sched_config is None:
            return None
        cfg = self.scheduler.config if self.scheduler is not None else self._sched_config
        return depth_rate_limit(cfg, self._spacing).depth_hz

    def frames_dropped(self) -> int:
        """Frames lost before the core: by the source, the estimator queue or the result queue."""
        source = self._parts.source
        estimator = self._parts.estimator
        return (
            (source.dropped_frames if source is not None else 0)
            + (estimator.dropped if estimator is not None else 0)
            + self.results_dropped
        )

    def _link_health(self, now: float) -> models.LinkHealth:
        link = self._parts.link
        if link is None:
            return models.LinkHealth(connected=False)
        h = link.health()
        age = None if h.last_reply_monotonic is None else max(0.0, now - h.last_reply_monotonic)
        return models.LinkHealth(
            connected=h.connected,
            bytes_in=h.bytes_in,
            bytes_out=h.bytes_out,
            replies=sum(h.replies.values()),
            errors=sum(h.errors_by_code.values()),
            timeouts=sum(h.timeouts.values()),
            last_reply_age_s=age,
            reconnects=h.reconnects,
        )

    def _frames_flowing(self, now: float) -> bool:
        return self._last_frame_mono is not None and now - self._last_frame_mono < (
            FRAMES_FLOWING_S
        )

    def _snapshot(self, now: float, status: models.Status) -> ConsoleSnapshot:
        rates = status.rates
        link = status.link
        mqtt = status.mqtt
        assert rates is not None
        assert link is not None
        assert mqtt is not None
        sched = self.scheduler
        pan, tilt = sched.pan_tilt_at(now) if sched is not None else (0.0, 0.0)
        return ConsoleSnapshot(
            camera=self.config.camera.name,
            state=self._state,
            uptime_s=now - self._t_start,
            frame_hz=rates.frame_hz,
            estimate_hz=rates.estimate_hz,
            depth_hz=rates.depth_hz,
            depth_limit_hz=rates.depth_limit_hz,
            link_connected=link.connected,
            link_timeouts=link.timeouts,
            link_errors=link.errors,
            link_reconnects=link.reconnects,
            mqtt_connected=mqtt.connected,
            mqtt_backlog=mqtt.backlog,
            frames_dropped=self.frames_dropped(),
            bursts_accepted=self.bursts_accepted,
            bursts_rejected=self.bursts_rejected,
            roles=dict(sched.stats.frames) if sched is not None else {},
            depth_m=self._last_depth,
            last_estimate_age_s=status.last_estimate_age_s,
            best=self.config.estimators.best,
            truth_z_m=self._last_truth_z,
            size_m=self._last_size,
            pan_deg=pan,
            tilt_deg=tilt,
        )


# -- helpers -------------------------------------------------------------------------------------
async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def _force_exit() -> None:
    _LOGGER.error("shutdown did not finish within %.0f s; exiting now", SHUTDOWN_TIMEOUT_S)
    logging.shutdown()
    os._exit(EXIT_FAILURE)


def _open_capture(config: DffdConfig) -> FrameSource:
    """The OpenCV frame source of ``[capture]`` (drivers/capture.py)."""
    from drivers.capture import CaptureSettings, OpenCVFrameSource

    cap = config.capture
    assert cap.device is not None  # validated: v4l2 needs a device
    settings = CaptureSettings(
        device=cap.device,
        width=cap.width,
        height=cap.height,
        fps=cap.fps,
        fourcc=cap.fourcc,
        buffer_size=1,  # one driver buffer: read() returns a fresh frame, not a stale one
        gray=True,  # the estimator's input
        queue_frames=CAPTURE_QUEUE_FRAMES,
        latency_s=cap.latency_frames / cap.fps,
    )
    return OpenCVFrameSource(settings)


def _scenario_world(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``[target]`` and ``[trajectory]`` tables of a world TOML (drivers/sim/data/worlds/).

    The tables are validated by the
    simulator's own config types (``drivers.sim.config.WorldConfig``) when applied.
    """
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DaemonError(
            f"sim.scenario: cannot read {path}: {exc.strerror}; give a scenario name "
            "(static, approach, paper-circle, figure-eight, random) or a TOML file path"
        ) from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise DaemonError(f"sim.scenario: {path} is not valid TOML: {exc}") from exc
    target = data.get("target", {})
    trajectory = data.get("trajectory")
    if not isinstance(trajectory, dict) or not isinstance(target, dict):
        raise DaemonError(
            f"sim.scenario: {path} needs a [trajectory] table (and optionally [target]) "
            "with the keys of drivers/sim/config.py TrajectoryConfig/TargetConfig"
        )
    return target, trajectory


def _fin(value: float | None) -> float | None:
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def _nonneg(value: float | None) -> float | None:
    v = _fin(value)
    return v if v is not None and v >= 0 else None


def _vec(value: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    x, y, z = (float(c) for c in value)
    if not all(math.isfinite(c) for c in (x, y, z)):
        return None
    return x, y, z


__all__ = [
    "CAMERA_INIT_TIMEOUT_S",
    "SHUTDOWN_TIMEOUT_S",
    "Daemon",
    "DaemonError",
    "EstimatorResult",
    "EstimatorThread",
    "RateMeter",
    "run",
]
