"""The simulated frame source: renders what the simulated camera sees, at its frame rate.

Frame ``k`` is exposed over ``[t_k − e/2, t_k + e/2]`` with ``t_k = t0 + k / fps`` (``Frame.t`` is
that mid-exposure time on the camera state's clock) and is delivered ``capture_latency_frames``
frame periods after the exposure ends — the frames in flight of a real capture chain. Pan, tilt,
focus and zoom come from the shared :class:`~drivers.sim.state.CameraState` *as they were during
the exposure* (the state keeps a short history), so VISCA commands over the serial link change
the view and the focus with the right timing.

Two ways to drive it:

* live: ``await start()`` then ``await next_frame()`` (the :class:`~drivers.frames.FrameSource`
  protocol); one render thread (``sim-render``) waits for each frame's delivery time, renders
  it and hands it to the event loop with one ``call_soon_threadsafe`` into a bounded
  drop-oldest queue — as a grabber's reader thread does, so the loop does no timing or
  executor work per frame;
* lock-step, in virtual time (benchmarks, tests): :meth:`SimFrameSource.render_frame` or
  :meth:`SimFrameSource.render` synchronously.

The ground truth of every rendered frame (:class:`FrameTruth`) is kept in a bounded table for
:meth:`SimFrameSource.truth_for`; it never travels in the :class:`~drivers.frames.Frame`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.frames import Frame, FrameSourceError
from drivers.sim.config import CaptureConfig, SimCameraConfig
from drivers.sim.optics import FrameView, Optics, TargetImage, average_kernels, project
from drivers.sim.optics import world_from_camera as _world_from_camera
from drivers.sim.state import CameraState, Clock
from drivers.sim.world import World, rms_radius

log = logging.getLogger(__name__)

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]

# Focus positions sampled across an exposure when the focus motor turns during it (their PSFs are
# averaged): enough for a smooth transit blur, cheap because PSFs are cached.
FOCUS_TRANSIT_SAMPLES = 5
# Nearest depth (m) in front of the optical centre that is still rendered.
MIN_DEPTH_M = 0.05
# Bound on one render hand-off while closing the live loop (a frame renders in a few ms).
CLOSE_TIMEOUT_S = 2.0
# The live render thread's name (the bench tells the simulator's CPU from the service's by it).
RENDER_THREAD_NAME = "sim-render"


@dataclass(frozen=True, slots=True)
class FrameTruth:
    """Ground truth of one rendered frame (for tests and the bench, never the estimator)."""

    index: int | None  # frame index (None for an ad-hoc render(t))
    t: float  # mid-exposure time, camera-state clock
    t_world: float  # scenario time (t − world epoch)
    position_world_m: Vec3  # target centre
    velocity_world_mps: Vec3
    position_camera_m: Vec3  # x right, y down, z along the optical axis
    z_m: float  # depth along the optical axis
    roll_deg: float  # target rotation about the line of sight
    size_m: float  # R, sqrt(tr Σ) of the real boundary
    centre_px: Vec2  # projection of the target centre
    centroid_px: Vec2  # centroid of the projected boundary (uniform arc-length samples)
    r_px: float  # sqrt(tr Σ) of the projected boundary
    in_view: bool  # the whole outline lies inside the frame
    pan_deg: float
    tilt_deg: float
    zoom_counts: float
    focus_counts: float  # actually in place at mid-exposure (commanded + repeatability error)
    focus_counts_commanded: float  # what the motor state says
    focal_length_mm: float
    v0_mm: float  # lens-to-sensor distance at mid-exposure
    v_mm: float  # lens-to-sensor distance at which the target is sharp
    blur_radius_px: float  # defocus blur-circle radius at mid-exposure
    focus_moving: bool  # the focus motor turned during the exposure (transit frame)
    pan_tilt_moving: bool
    zoom_moving: bool
    motion_px: Vec2  # image displacement of the target centre during the exposure
    powered: bool
    acceleration_world_mps2: Vec3 = (0.0, 0.0, 0.0)  # target centre, world frame
    angular_speed_rad_s: float = 0.0  # turn rate about the upward vertical (drivers/sim/world.py)


class SimFrameSource:
    """Frames of the simulated camera (implements :class:`drivers.frames.FrameSource`)."""

    def __init__(
        self,
        state: CameraState,
        world: World,
        optics: Optics,
        capture: CaptureConfig | None = None,
        *,
        seed: int = 0,
        t0: float | None = None,
        world_epoch: float | None = None,
    ) -> None:
        self.state = state
        self.world = world
        self.optics = optics
        self.capture = capture or CaptureConfig()
        self._clock: Clock = state.clock
        self._seed = seed
        self.t0 = state.now() if t0 is None else t0  # mid-exposure time of frame 0
        self.world_epoch = self.t0 if world_epoch is None else world_epoch
        self._sensor = optics.make_sensor()
        self._render_lock = threading.Lock()
        # The truth table has a lock of its own: a reader (the daemon's loop, for the frame it
        # just received) must not wait for the next frame's render (3-10 ms) to finish.
        self._truth_lock = threading.Lock()
        self._truth: OrderedDict[int, FrameTruth] = OrderedDict()
        self._jitter_rng = np.random.default_rng([seed, 0x4A17])
        self._jitter = 0.0
        self._last_render_t: float | None = None
        self._adhoc = 0
        self._dropped = 0
        self._queue: deque[Frame] = deque()
        self._ready = asyncio.Event()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._failure: BaseException | None = None  # what ended the render thread
        self._closed = False

    @classmethod
    def from_config(
        cls,
        config: SimCameraConfig,
        state: CameraState,
        world: World | None = None,
        *,
        t0: float | None = None,
    ) -> SimFrameSource:
        """A source for a whole simulated-camera config (world from the config unless given)."""
        return cls(
            state,
            world if world is not None else World.from_config(config.world),
            Optics.from_config(config),
            config.capture,
            seed=config.seed,
            t0=t0,
        )

    # -- FrameSource protocol ----------------------------------------------------------------
    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.optics.frame_size

    @property
    def fps(self) -> float:
        """Frame rate."""
        return self.capture.fps

    @property
    def dropped_frames(self) -> int:
        """Frames rendered late or overwritten before the caller took them."""
        return self._dropped

    async def start(self) -> None:
        """Begin rendering in real time from the next frame slot."""
        if self._closed:
            raise FrameSourceError("simulated frame source is closed; create a new one")
        if self._thread is None:
            self._ready = asyncio.Event()
            first = max(0, math.ceil((self._clock() - self.t0) * self.fps))
            self._thread = threading.Thread(
                target=self._run,
                args=(asyncio.get_running_loop(), first),
                name=RENDER_THREAD_NAME,
                daemon=True,
            )
            self._thread.start()

    async def next_frame(self) -> Frame:
        """The oldest undelivered frame (wrap in ``asyncio.timeout``)."""
        if self._thread is None:
            raise FrameSourceError("simulated frame source not started; call start() first")
        while not self._queue:
            if self._closed:
                raise FrameSourceError("simulated frame source closed")
            if self._failure is not None:
                exc = self._failure
                raise FrameSourceError(f"simulated frame source stopped: {exc!r}") from exc
            self._ready.clear()
            await self._ready.wait()
        return self._queue.popleft()

    async def close(self) -> None:
        """Stop rendering; idempotent."""
        self._closed = True
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread.is_alive():
            # The thread notices the stop within one render (a few ms).
            await asyncio.to_thread(thread.join, CLOSE_TIMEOUT_S)
        self._ready.set()

    # -- lock-step / ground truth ------------------------------------------------------------
    def frame_time(self, index: int) -> float:
        """Mid-exposure time of frame ``index``."""
        return self.t0 + index / self.fps

    def delivery_time(self, index: int) -> float:
        """When frame ``index`` leaves the capture chain."""
        return (
            self.frame_time(index)
            + 0.5 * self.capture.exposure_s
            + self.capture.capture_latency_frames / self.fps
        )

    def render_frame(self, index: int) -> Frame:
        """Render frame ``index`` now (any thread) and record its truth."""
        t = self.frame_time(index)
        image, _truth = self._render(t, index)
        return Frame(index, t, image)

    def render(self, t: float) -> tuple[npt.NDArray[np.uint8], FrameTruth]:
        """Render an exposure centred at ``t`` (not recorded in the truth table)."""
        return self._render(t, None)

    def focus_oracle(self, t: float) -> float:
        """Focus counts that make the target sharp at time ``t`` (an ideal AF's choice).

        Pass as ``ViscaDevice(focus_oracle=source.focus_oracle)`` for One Push AF.
        """
        mid = self.state.snapshot(t)
        pose = self.world.pose(t - self.world_epoch)
        z = float((pose.position_m @ _world_from_camera(mid.pan_deg, mid.tilt_deg))[2])
        low, high = self.state.focus_limits
        if z <= MIN_DEPTH_M:
            return low
        return min(high, max(low, self.optics.focus_counts_for_depth(z)))

    def truth_for(self, index: int) -> FrameTruth | None:
        """Ground truth of a recently rendered frame (None if unknown or evicted)."""
        with self._truth_lock:
            return self._truth.get(index)

    def truth_near(self, t: float | None) -> FrameTruth | None:
        """Ground truth of the recent frame exposed nearest ``t`` (within half a period)."""
        if t is None:
            return None
        truth = self.truth_for(round((t - self.t0) * self.fps))
        if truth is None or abs(truth.t - t) > 0.5 / self.fps:
            return None
        return truth

    # -- internals ---------------------------------------------------------------------------
    def _run(self, loop: asyncio.AbstractEventLoop, index: int) -> None:
        """The render thread: each frame at its delivery time, handed to the loop once."""
        period = 1.0 / self.fps
        try:
            while not self._stop.is_set():
                delay = self.delivery_time(index) - self._clock()
                if delay > 0 and self._stop.wait(delay):
                    return
                late = math.floor((self._clock() - self.delivery_time(index)) / period)
                if late > 0:  # rendering fell behind: those exposures are lost, as on a grabber
                    self._dropped += late
                    log.debug("simulated capture %d frame(s) late; dropped", late)
                    index += late
                frame = self.render_frame(index)
                try:
                    loop.call_soon_threadsafe(self._deliver, frame)
                except RuntimeError:  # the event loop closed under the thread: nobody waits
                    return
                index += 1
        except Exception as exc:  # noqa: BLE001 - next_frame() raises it on the loop
            self._failure = exc
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._ready.set)

    def _deliver(self, frame: Frame) -> None:
        """On the loop: queue a rendered frame (dropping the oldest) and wake the consumer."""
        if self._closed:
            return
        if len(self._queue) >= self.capture.queue_frames:
            self._queue.popleft()
            self._dropped += 1
        self._queue.append(frame)
        self._ready.set()

    def _render(self, t: float, index: int | None) -> tuple[npt.NDArray[np.uint8], FrameTruth]:
        with self._render_lock:
            start = time.perf_counter()
            image, truth = self._render_locked(t, index)
            if index is not None:
                with self._truth_lock:
                    self._truth[index] = truth
                    while len(self._truth) > self.capture.truth_frames:
                        self._truth.popitem(last=False)
            log.debug("rendered frame %s in %.2f ms", index, 1e3 * (time.perf_counter() - start))
            return image, truth

    def _render_locked(
        self, t: float, index: int | None
    ) -> tuple[npt.NDArray[np.uint8], FrameTruth]:
        optics, world, state = self.optics, self.world, self.state
        half = 0.5 * self.capture.exposure_s
        t_a, t_b = t - half, t + half
        with state.lock:
            mid = state.snapshot(t)
            start, end = state.snapshot(t_a), state.snapshot(t_b)
            focus_moving = state.focus.moved_between(t_a, t_b)
            pan_tilt_moving = state.pan.moved_between(t_a, t_b) or state.tilt.moved_between(
                t_a, t_b
            )
            zoom_moving = state.zoom.moved_between(t_a, t_b)
            focus_samples = (
                [
                    state.focus.position(t_a + (k + 0.5) * (t_b - t_a) / FOCUS_TRANSIT_SAMPLES)
                    for k in range(FOCUS_TRANSIT_SAMPLES)
                ]
                if focus_moving
                else [mid.focus_counts]
            )
            moved_since_last = self._last_render_t is None or state.focus.moved_between(
                min(self._last_render_t, t_a), t_b
            )
        self._last_render_t = t_b
        if moved_since_last and optics.lens.focus_jitter_counts > 0.0:
            self._jitter = float(self._jitter_rng.normal(0.0, optics.lens.focus_jitter_counts))
        zoom = mid.zoom_counts
        focus_actual = mid.focus_counts + self._jitter
        v0 = optics.lens_to_sensor_mm(focus_actual, zoom)
        scale = optics.scale_px(v0, zoom)
        principal = optics.principal_point_px

        pose = world.pose(t - self.world_epoch)
        rotation = _world_from_camera(mid.pan_deg, mid.tilt_deg)
        cam = pose.position_m @ rotation
        z = float(cam[2])
        visible = mid.powered and z > MIN_DEPTH_M
        v = optics.sharp_v_mm(z, zoom) if z * 1000.0 > optics.focal_length_mm(zoom) else math.inf
        v0_samples = [optics.lens_to_sensor_mm(c + self._jitter, zoom) for c in focus_samples]
        blurs = (
            [optics.blur_radius_px(v0_i, v, zoom) for v0_i in v0_samples]
            if math.isfinite(v)
            else [0.0]
        )
        boundary_px, boundary_z = project(
            world.boundary_world(pose), mid.pan_deg, mid.tilt_deg, scale, principal
        )
        centre_uv, _ = project(
            pose.position_m[None, :], mid.pan_deg, mid.tilt_deg, scale, principal
        )
        visible = visible and bool(np.all(boundary_z > MIN_DEPTH_M))

        motion = (0.0, 0.0)
        if visible and self.capture.motion_blur:
            p_a, _ = project(
                world.pose(t_a - self.world_epoch).position_m[None, :],
                start.pan_deg,
                start.tilt_deg,
                scale,
                principal,
            )
            p_b, _ = project(
                world.pose(t_b - self.world_epoch).position_m[None, :],
                end.pan_deg,
                end.tilt_deg,
                scale,
                principal,
            )
            motion = (float(p_b[0, 0] - p_a[0, 0]), float(p_b[0, 1] - p_a[0, 1]))

        patch = None
        if visible:
            outline_px, _ = project(
                world.outline_world(pose), mid.pan_deg, mid.tilt_deg, scale, principal
            )
            corners_w = world.texture_corners_world(pose)
            corners_px = (
                None
                if corners_w is None
                else project(corners_w, mid.pan_deg, mid.tilt_deg, scale, principal)[0]
            )
            kernels = (
                [optics.defocus_psf(v0_i, v, zoom) for v0_i in v0_samples]
                if math.isfinite(v)
                else [optics.psf(0.0)]
            )
            kernel = average_kernels(kernels) if len(kernels) > 1 else kernels[0]
            target = TargetImage(
                outline_px,
                world.shape.foreground_dn,
                world.shape.texture,
                corners_px,
                texture_nearest=world.shape.kind == "aruco",
            )
            patch = optics.render_target(target, world.background_dn, kernel, motion)
        background = world.background_dn if mid.powered else 0.0
        view = FrameView(mid.pan_deg, mid.tilt_deg, v0, zoom)
        image = self._sensor.expose(background, patch, self._noise_seed(t, index), view)

        width, height = optics.frame_size
        in_view = visible and bool(
            np.all(
                (boundary_px[:, 0] >= -0.5)
                & (boundary_px[:, 0] <= width - 0.5)
                & (boundary_px[:, 1] >= -0.5)
                & (boundary_px[:, 1] <= height - 0.5)
            )
        )
        finite = bool(np.all(np.isfinite(boundary_px)))
        centroid = boundary_px.mean(axis=0) if finite else np.array([math.nan, math.nan])
        truth = FrameTruth(
            index=index,
            t=t,
            t_world=t - self.world_epoch,
            position_world_m=_vec3(pose.position_m),
            velocity_world_mps=_vec3(pose.velocity_mps),
            position_camera_m=_vec3(cam),
            z_m=z,
            roll_deg=math.degrees(pose.roll_rad),
            size_m=world.shape.size_m,
            centre_px=(float(centre_uv[0, 0]), float(centre_uv[0, 1])),
            centroid_px=(float(centroid[0]), float(centroid[1])),
            r_px=rms_radius(boundary_px) if finite else math.nan,
            in_view=in_view,
            pan_deg=mid.pan_deg,
            tilt_deg=mid.tilt_deg,
            zoom_counts=zoom,
            focus_counts=focus_actual,
            focus_counts_commanded=mid.focus_counts,
            focal_length_mm=optics.focal_length_mm(zoom),
            v0_mm=v0,
            v_mm=v,
            blur_radius_px=blurs[len(blurs) // 2],
            focus_moving=focus_moving,
            pan_tilt_moving=pan_tilt_moving,
            zoom_moving=zoom_moving,
            motion_px=motion,
            powered=mid.powered,
            acceleration_world_mps2=_vec3(pose.acceleration_mps2),
            angular_speed_rad_s=pose.angular_speed_rad_s,
        )
        return image, truth

    def _noise_seed(self, t: float, index: int | None) -> int:
        if index is None:
            self._adhoc += 1
            key = [self._seed, 1, self._adhoc]
        else:
            key = [self._seed, 0, index]
        return int(np.random.SeedSequence(key).generate_state(1)[0])


def camera_state_for(config: SimCameraConfig, clock: Clock = time.monotonic) -> CameraState:
    """A camera state at the config's fixed zoom, focused at infinity."""
    return CameraState(
        clock=clock,
        initial_zoom=config.zoom_counts,
        initial_focus=config.lens.focus_far_counts,
    )


def _vec3(v: npt.NDArray[np.float64]) -> Vec3:
    return float(v[0]), float(v[1]), float(v[2])
