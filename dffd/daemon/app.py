"""The daemon of ``dffd run`` — camera, capture, scheduler, estimator thread, MQTT, log, systemd.

The asyncio shell (design.md §2) only moves bytes, frames and messages; every decision is made by
the pure :class:`~dffd.scheduler.Scheduler` and the estimation core. Layout at run time:

* tasks under one ``asyncio.TaskGroup``: **capture** (frame source → scheduler tag → estimator
  queue), **scheduler** (wakes on events and on the scheduler's own wake-up time, dispatches its
  actions), **focus** and **pan/tilt** workers (one action in flight each, on the camera's two
  VISCA sockets at once), **results** (estimator output → MQTT + JSONL log + scheduler
  feedback), **status** (retained status, console, sd_notify watchdog), and the MQTT
  **publisher**;
* ONE estimator thread running the core behind ONE bounded frame queue (drop-oldest, counted:
  capture never blocks); results come back in ONE hand-off per frame: a bounded buffer
  (drop-oldest, counted) and one ``loop.call_soon_threadsafe`` that handles them on the loop
  at once (payloads, MQTT, JSONL log, scheduler feedback), without a queue and a task switch
  between. Commands that change the core (acquire, release, known size) are applied by that
  thread between frames, so the core is never touched concurrently.

This module is the shell; each part is a module of its own: :mod:`~dffd.daemon.estimator` (the
thread and its queue), :mod:`~dffd.daemon.actuators` (the focus and pan/tilt workers),
:mod:`~dffd.daemon.commands`, :mod:`~dffd.daemon.status` (rates, the status payload, the
console row), :mod:`~dffd.daemon.payloads` (core outputs → MQTT models) and
:mod:`~dffd.daemon.dashboard`. The objects are built from the configuration by
:mod:`dffd.wiring`, as the bench and ``dffd replay`` build them.

Start-up (embedded broker, the simulated or real camera, the frame source, camera
initialisation) is :mod:`~dffd.daemon.startup`; the command that runs one :class:`Daemon`
(arguments, log levels, the terminal) is :mod:`~dffd.daemon.cli`.

:class:`Daemon` is one class of ~560 lines kept whole: its start-up, tasks, result hand-off,
status and shutdown share what it started (held for orderly shutdown), the wake event, the
estimator's result buffer and the future that ends the run on a failed result, the publisher,
the scheduler and the status board; split, each part would reach into the others' state. What
stands alone is a module of its own (above).

Acquisition (the same live and on the simulator): the lens goes to
``scheduler.initial_focus_depth_m``; every frame reaches the core, those of the start-up focus
move too (a target crossing the view fast is caught only there; :mod:`dffd.step`); bursts
start after ``acquire_stable_frames`` frames with a contour; pan/tilt follows with velocity
feed-forward from the first two centroids; after a loss the head searches along the target's
predicted path, then returns to where it was last seen, while the core keeps searching (see
:mod:`dffd.scheduler`). Automatic acquisition (a start without ``[target] roi``, ``acquire``
without an ROI, a loss) that sees nothing for ``scheduler.search_after_s`` sweeps pan/tilt over
the camera's range until the target shows (:mod:`dffd.scheduler.search`; logged and reported by
:mod:`~dffd.daemon.searchwatch`); ``release`` never searches.

Shutdown (SIGTERM/SIGINT): stop pan/tilt, publish the retained ``offline`` status, flush the
JSONL log, say so on the console, exit 0 — all within :data:`SHUTDOWN_TIMEOUT_S`. On a
terminal the daemon takes the foreground process group while it runs (:mod:`~dffd.daemon.cli`,
:mod:`dffd.cli.terminal`), so Ctrl-C under ``make run`` stops dffd alone and make returns 0.
sd_notify READY is sent once the camera is initialised and frames flow; WATCHDOG pings come
from the status task only while frames flow.

Exit codes: 0 clean stop, 1 runtime failure (camera, broker, capture, log), 2 configuration,
130 interrupted while still loading (before the daemon could stop in order).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from dffd.config import DffdConfig
from dffd.core.lens import Lens, LensError
from dffd.daemon.actuators import Actuators
from dffd.daemon.commands import Commands
from dffd.daemon.console import Console, ConsoleSnapshot
from dffd.daemon.estimator import EstimatorResult, EstimatorThread
from dffd.daemon.jsonlog import JsonlLog, JsonlLogError
from dffd.daemon.notify import Notifier
from dffd.daemon.payloads import Payloads, truth_payload, without_depth
from dffd.daemon.searchwatch import SearchWatch
from dffd.daemon.startup import (
    CAMERA_INIT_TIMEOUT_S,
    DaemonError,
    initialize_camera,
    link_timeouts,
    open_source,
    start_broker,
    start_camera_transport,
)
from dffd.daemon.status import StatusBoard, link_health, video_health
from dffd.daemon.timeline import StartTimeline
from dffd.exitcodes import EXIT_FAILURE, EXIT_OK
from dffd.mqtt import models
from dffd.mqtt.commands import CommandRejected
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics
from dffd.scheduler import Action, Scheduler, SchedulerConfig, depth_rate_limit
from dffd.web.interface import Snapshot
from dffd.web.listen import WebConfigError
from dffd.wiring import (
    arm_search,
    build_core,
    scheduler_config,
)
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
# A frame must arrive within this time (30 fps → 33 ms; a USB grabber may stall ~1 s on
# re-negotiation) before capture is reported stalled (it then keeps waiting).
FRAME_TIMEOUT_S = 2.0
# Status (retained), console and watchdog period. Also the rate window's granularity.
STATUS_PERIOD_S = 1.0
# The scheduler task sleeps at most this long without an event (guards against a lost wake-up).
# Shortest wait when the scheduler asks to be woken in the past but has nothing to do: far
# below its timing resolution (one video field, 16.7 ms), so it costs no accuracy, yet it keeps
# a past wake-up from becoming a busy loop.
SCHEDULER_MIN_WAIT_S = 0.001
SCHEDULER_IDLE_S = 0.5
# Bounded queues (docs/design.md §10: no unbounded queue anywhere).
RESULT_QUEUE_MAX = 64  # estimator output waiting for the event loop


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
        self.timeline = StartTimeline()  # the start-up's steps, logged at DEBUG
        self.timeline.mark("imported, configuration loaded")
        self.sim_faults = sim_faults
        self.duration_s = duration_s
        self.console = Console(live=live_console)
        self.notifier = Notifier()
        self.topics = Topics(config.mqtt.topic_prefix, config.camera.name)
        self.stop_requested = asyncio.Event()
        self._parts = _Parts()
        self._wake = asyncio.Event()
        # Estimator output waiting for the loop (see _hand_over): filled by the estimator thread,
        # drained on the loop; one call_soon_threadsafe per drain.
        self._results: deque[EstimatorResult] = deque()
        self._results_lock = threading.Lock()
        self._drain_pending = False
        self._results_failed: asyncio.Future[None] | None = None
        self.results_dropped = 0
        self.payloads = Payloads(config.estimators.best)
        self.board = StatusBoard(config.camera.name, config.estimators.best, time.monotonic())
        self._ready_sent = False
        self._commands: Commands | None = None
        self.camera: Camera | None = None
        self.scheduler: Scheduler | None = None
        self._search_watch: SearchWatch | None = None
        self.publisher: Publisher | None = None
        self._sched_config: SchedulerConfig | None = None
        self.dashboard: Dashboard | None = None
        self._web: WebSettings | None = None
        self.board.known_size_m = config.target.known_size_m
        self.stop_reason: str | None = None  # what stopped the run (for the farewell)
        self.shutdown_problems: list[str] = []  # what did not go as it should at shutdown

    # -- lifecycle ------------------------------------------------------------------------------
    async def main(self) -> int:
        """Start everything, run until stopped, shut down; return the exit code."""
        loop = asyncio.get_running_loop()
        for sig, reason in ((signal.SIGTERM, "SIGTERM"), (signal.SIGINT, "Ctrl-C (SIGINT)")):
            loop.add_signal_handler(sig, self.request_stop, reason)
        code = EXIT_OK
        errors: list[str] = []
        try:
            with self.console:
                try:
                    await self._run()
                except* DaemonError as group:
                    errors += [str(error) for error in group.exceptions]
                    for error in group.exceptions:
                        _LOGGER.error("%s", error)
                    code = EXIT_FAILURE
                except* (ViscaError, FrameSourceError, JsonlLogError, OSError) as failures:
                    errors += [str(failure) for failure in failures.exceptions]
                    for failure in failures.exceptions:
                        _LOGGER.error("dffd stopped: %s", failure)
                    code = EXIT_FAILURE
            self.console.farewell(self.farewell(code, errors, time.monotonic()))
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
        return code

    def farewell(self, code: int, errors: list[str], now: float) -> str:
        """The last line of a run: why it stopped, what it did, whether shutdown was clean."""
        ran = now - self.board.t_start
        done = (
            f"after {ran:.0f} s: {self.board.estimates.count} estimates, "
            f"{self.board.measurements.count} depth measurements"
        )
        if code != EXIT_OK:
            return f"dffd failed {done}: {'; '.join(errors) or 'see the log above'} (exit {code})"
        why = self.stop_reason or "request"
        if self.shutdown_problems:
            return (
                f"dffd stopped on {why} {done}, with problems: "
                f"{'; '.join(self.shutdown_problems)} (exit {code})"
            )
        return (
            f"dffd stopped cleanly on {why} {done}; pan/tilt stopped, retained status "
            f"'offline' published, log flushed (exit {code})"
        )

    def request_stop(self, reason: str = "request") -> None:
        """Begin an orderly shutdown (signal handler; idempotent)."""
        if not self.stop_requested.is_set():
            self.stop_reason = reason
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
        self.timeline.mark("estimation core built")
        self.dashboard = dashboard.Dashboard(
            self.dashboard_snapshot,
            self._execute,
            normal_half_px=float(core.pipeline.config.search_px),
            counts_range=lens.counts_range,
        )
        try:
            async with contextlib.AsyncExitStack() as stack:
                self.timeline.mark("dashboard built")
                self._parts.broker = await start_broker(cfg, stack)
                self.timeline.mark("broker up")
                port, self._parts.sim_server, rig = await start_camera_transport(
                    cfg, stack, self.sim_faults
                )
                self.timeline.mark("camera transport up")
                source, exposure_s, focus_speed, truth_for = await open_source(cfg, rig, stack)
                self._parts.source = source
                self._parts.truth_for = truth_for
                stack.push_async_callback(self._source_close)
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
                self._search_watch = SearchWatch(self.scheduler, self.board)
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
                estimator = EstimatorThread(core, lambda r: self._hand_over(loop, r))
                estimator.start()
                self._parts.estimator = estimator
                assert self.scheduler is not None
                self._commands = Commands(
                    cfg,
                    self.scheduler,
                    estimator,
                    camera=lambda: self.camera,
                    wake=self._wake.set,
                    acquired=self._acquired,
                    released=self._released,
                )
                stack.callback(estimator.stop)
                self.timeline.mark("estimator thread started")
                await self._serve(port, source, lens)
        except TimeoutError as exc:
            raise DaemonError(f"start-up timed out: {exc or 'no answer'}") from exc

    async def _serve(self, port: str, source: FrameSource, lens: Lens) -> None:
        cfg = self.config
        assert self.publisher is not None
        publisher = self.publisher
        try:
            link = ViscaLink(port, cfg.camera.baudrate, timeouts=link_timeouts(cfg))
        except ValueError as exc:  # a bad URL; the config's validation parses camera.port first
            where = "camera.port" if cfg.camera.driver == "visca" else "simulated camera's port"
            raise DaemonError(f"{where}: {exc}") from exc
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
                    assert self.scheduler is not None
                    self.timeline.mark("VISCA link open")
                    await initialize_camera(
                        camera, lens, cfg.lens.zoom_counts, self.scheduler, self._wake.set,
                        cfg.camera.model,
                    )  # fmt: skip
                    self.timeline.mark("camera initialised")
                    self.camera = camera
                    actuators = Actuators(camera, self.scheduler, self._wake.set)
                    await source.start()
                    self.timeline.mark("frame source started")
                    # Automatic acquisition sweeps if nothing is in view; an ROI does not.
                    arm_search(self.scheduler, cfg, time.monotonic())
                    self._results_failed = asyncio.get_running_loop().create_future()
                    tasks = [
                        group.create_task(self._capture_loop(source), name="capture"),
                        group.create_task(
                            self._scheduler_loop(actuators.dispatch), name="scheduler"
                        ),
                        group.create_task(actuators.run_focus(), name="focus"),
                        group.create_task(actuators.run_pan_tilt(), name="pan-tilt"),
                        group.create_task(self._results_loop(self._results_failed), name="results"),
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
        self.request_stop(f"--duration {self.duration_s:g} s")

    async def _shutdown_camera(self, camera: Camera) -> None:
        try:
            async with asyncio.timeout(PAN_TILT_STOP_TIMEOUT_S):
                await camera.pan_tilt_stop()
            _LOGGER.info("pan/tilt stopped")
        except (ViscaError, TimeoutError) as exc:
            _LOGGER.warning("could not stop pan/tilt at shutdown: %s", exc)
            self.shutdown_problems.append(f"pan/tilt not stopped ({exc or 'timeout'})")
        await self._source_close()

    async def _source_close(self) -> None:
        source = self._parts.source
        if source is not None:
            with contextlib.suppress(FrameSourceError, TimeoutError):
                async with asyncio.timeout(PAN_TILT_STOP_TIMEOUT_S):
                    await source.close()

    async def _shutdown_publisher(self, publisher: Publisher, task: asyncio.Task[None]) -> None:
        if not publisher.connected:
            self.shutdown_problems.append("MQTT not connected, so 'offline' was not published")
        publisher.publish(publisher.status_payload("offline", "stopped"))
        await publisher.stop()
        if not task.done():
            task.cancel()

    async def _close_log(self) -> None:
        log = self._parts.log
        if log is not None and not await log.aclose():
            _LOGGER.error("JSONL log did not flush in time; the last records may be missing")
            self.shutdown_problems.append("JSONL log not flushed in time")

    # -- tasks ---------------------------------------------------------------------------------
    async def _capture_loop(self, source: FrameSource) -> None:
        sched = self.scheduler
        estimator = self._parts.estimator
        assert sched is not None
        assert estimator is not None
        stalled = False
        first = True
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
            if first:
                first = False
                self.timeline.mark("first frame")
            now = time.monotonic()
            self.board.on_frame(now)
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
        self.board.last_truth_z = float(truth.z_m)
        assert self.publisher is not None
        self.publisher.publish(truth_payload(frame.t, truth))

    async def _scheduler_loop(self, dispatch: Callable[[Action], object]) -> None:
        sched = self.scheduler
        watch = self._search_watch  # None only in tests that drive this loop alone
        assert sched is not None
        while True:
            now = time.monotonic()
            actions = sched.next_actions(now)
            for action in actions:
                _LOGGER.debug("action at %.4f: %r", now, action)
                dispatch(action)
            if watch is not None and watch.update(now):
                self._publish_status(now)
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

    def _hand_over(self, loop: asyncio.AbstractEventLoop, result: EstimatorResult) -> None:
        """In the estimator thread: buffer a result (dropping the oldest beyond
        :data:`RESULT_QUEUE_MAX`) and wake the loop once for everything buffered."""
        with self._results_lock:
            if len(self._results) >= RESULT_QUEUE_MAX:
                self._results.popleft()
                self.results_dropped += 1
            self._results.append(result)
            if self._drain_pending:  # the loop has not drained the last wake-up's yet
                return
            self._drain_pending = True
        loop.call_soon_threadsafe(self._drain_results)

    def _drain_results(self) -> None:
        """On the loop: handle every buffered result now, in order."""
        with self._results_lock:
            batch = list(self._results)
            self._results.clear()
            self._drain_pending = False
        for result in batch:
            try:
                self._on_result(result)
            except Exception as exc:  # ends the results task, and with it the run (as before)
                failed = self._results_failed
                if failed is None or failed.done():
                    raise
                failed.set_exception(exc)
                return

    async def _results_loop(self, failed: asyncio.Future[None]) -> None:
        """Results are handled in :meth:`_drain_results`; this task ends the run with the
        exception one of them raised (a JSONL log failure, a bug), as a task of its own would."""
        try:
            await failed
        finally:
            self._results_failed = None

    def _on_result(self, result: EstimatorResult) -> None:
        """On the loop: publish, log and feed back one processed frame."""
        sched = self.scheduler
        log = self._parts.log
        publisher = self.publisher
        assert sched is not None
        assert log is not None
        assert publisher is not None
        failed = self._results_failed
        if failed is None or failed.done():  # not serving (starting or stopping): nothing to do
            return
        now = time.monotonic()
        out = result.step.output
        self.board.state = out.state
        if out.state == "tracking":
            self.board.message = None  # a release's or an acquire's note is over
        if self.dashboard is not None:
            self.dashboard.on_result(result.frame, result.step, result.cpu_s)
        if out.measurement is not None:
            if not self.timeline.marked("first depth published"):
                m = out.measurement
                self.timeline.event(f"burst {m.focus_counts} closed: z {m.z_m} ({m.reason})")
            self.board.on_measurement(now, out.measurement)
            payload_m = self.payloads.measurement(out.measurement)
            if payload_m is not None:
                log.append("measurement", payload_m)
                publisher.publish(payload_m)
                if self.dashboard is not None:
                    self.dashboard.on_measurement(payload_m)
        payload_e = None
        if out.estimate is not None:
            payload_e = self.payloads.estimate(out.estimate, result.step.track)
            # the core step's first-depth gate (dffd.first_depth): held back, the depths go null
            if payload_e is not None and not result.step.published:
                payload_e = without_depth(payload_e)
        if payload_e is not None:
            self.timeline.mark("first estimate published")
            if payload_e.z_m is not None:
                self.timeline.mark("first depth published")
            self.board.on_estimate(now, payload_e)
            log.append("estimate", payload_e)
            publisher.publish(payload_e)
            if self.dashboard is not None:
                self.dashboard.on_estimate(payload_e, self._truth_z(result.frame_index), now)
        feedback = result.step.feedback
        if feedback.plan is not None:
            self.board.on_plan(feedback.plan)
        feedback.apply(sched)
        self._wake.set()

    async def _status_loop(self) -> None:
        publisher = self.publisher
        assert publisher is not None
        while True:
            now = time.monotonic()
            flowing = self.board.frames_flowing(now)
            if flowing and not self._ready_sent:
                self.notifier.ready("camera initialised, frames flowing")
                self._ready_sent = True
                _LOGGER.info("ready: camera initialised and frames flowing")
            if flowing:
                self.notifier.watchdog()
            self._publish_status(now)
            await asyncio.sleep(STATUS_PERIOD_S)

    def _publish_status(self, now: float) -> None:
        """Publish the retained status and show it on the console (periodically, and at once
        when the search sweep starts, ends or gives up)."""
        publisher = self.publisher
        assert publisher is not None
        # A status that cannot be built must not end the status task (and with it the watchdog
        # pings): skip that period, counted like any other unpublishable payload.
        status = self.payloads.or_none(self.status_payload, now)
        if status is not None:
            publisher.publish(status)
            self.console.update(self._snapshot(now, status))

    # -- commands ------------------------------------------------------------------------------
    async def _on_command(self, command: models.Command) -> dict[str, Any] | None:
        commands = self._commands
        if commands is None:
            raise CommandRejected("the daemon is still starting; retry in a few seconds")
        result = await commands.execute(command)
        if isinstance(command, models.SetKnownSize):
            self.board.known_size_m = command.size_m
        return result

    def _acquired(self, roi: tuple[int, int, int, int] | None) -> None:
        self._set_roi(roi)
        self.board.on_acquire(roi)

    def _released(self) -> None:
        self._drop_pending_results()
        self._set_roi(None)
        self.board.on_release()

    # -- payloads --------------------------------------------------------------------------------
    def status_payload(self, now: float) -> models.Status:
        """The retained ``…/status`` payload now."""
        publisher = self.publisher
        assert publisher is not None
        stats = publisher.stats()
        log = self._parts.log
        drops = models.Drops(
            frames=self.frames_dropped(),
            publish_queue=stats.queue_dropped,
            backlog=stats.backlog_dropped,
            log=log.stats().dropped if log is not None else 0,
        )
        return self.board.status(
            now,
            depth_limit_hz=self.depth_limit_hz(),
            link=link_health(self._parts.link, now),
            mqtt=publisher.health(),
            drops=drops,
            video=video_health(self._parts.source),
        )

    def dashboard_snapshot(self) -> Snapshot | None:
        """The dashboard's view now (None until the publisher exists)."""
        if self.publisher is None:
            return None
        now = time.monotonic()
        source = self._parts.source
        return Snapshot(
            status=self.status_payload(now),
            last_estimate_age_s=self.board.estimate_age(now),
            bursts_accepted=self.board.bursts_accepted,
            bursts_rejected=self.board.bursts_rejected,
            frame_size=source.frame_size if source is not None else None,
            message=self.board.search_message(now) or self.board.message,
        )

    async def _execute(self, payload: bytes) -> models.CommandReply:
        """A dashboard command, through the MQTT command path (same validation and reply)."""
        if self.publisher is None:
            return models.CommandReply(
                id=None, ok=False, error="the daemon is still starting; retry",
                t=models.wall_time(),
            )  # fmt: skip
        return await self.publisher.execute(payload)

    def _truth_z(self, frame_index: int) -> float | None:
        truth_for = self._parts.truth_for
        truth = truth_for(frame_index) if truth_for is not None else None
        return None if truth is None else float(truth.z_m)

    def _set_roi(self, roi: tuple[int, int, int, int] | None) -> None:
        if self.dashboard is not None:
            self.dashboard.roi = roi

    def _drop_pending_results(self) -> None:
        """Forget results of frames processed before a release: nothing stale is published."""
        with self._results_lock:
            self._results.clear()

    def depth_limit_hz(self) -> float | None:
        """Theoretical depth-measurement rate of this configuration at the current spacing."""
        if self._sched_config is None:
            return None
        cfg = self.scheduler.config if self.scheduler is not None else self._sched_config
        return depth_rate_limit(cfg, self.board.spacing).depth_hz

    def frames_dropped(self) -> int:
        """Frames lost before the core: by the source, the estimator queue or the result queue."""
        source = self._parts.source
        estimator = self._parts.estimator
        return (
            (source.dropped_frames if source is not None else 0)
            + (estimator.dropped if estimator is not None else 0)
            + self.results_dropped
        )

    def _snapshot(self, now: float, status: models.Status) -> ConsoleSnapshot:
        sched = self.scheduler
        return self.board.snapshot(
            now,
            status,
            roles=dict(sched.stats.frames) if sched is not None else {},
            pan_tilt_deg=sched.pan_tilt_at(now) if sched is not None else (0.0, 0.0),
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


__all__ = [
    "CAMERA_INIT_TIMEOUT_S",
    "SHUTDOWN_TIMEOUT_S",
    "Daemon",
    "DaemonError",
]
