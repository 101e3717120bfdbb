"""``dffd calibrate --latency``: the delay from a frame's mid-exposure to its delivery, in seconds.

For a network stream (or any video source) ``[capture] latency_s``. The camera and the video of
``--config`` are started exactly as ``dffd run`` starts them (a real camera, or the simulator
with ``sim.video = "http"``), but frames are stamped with their plain arrival time.

Method: a small pan move is commanded (2° at 20°/s: any scene with an edge in view shifts by tens
of pixels at once, where a focus step may barely change a blurred scene) and the first frame
that shows it is found by image change (8×8 block means, above 3× the change between frames at
rest). That frame's exposure is the first to overlap the move, so its mid-exposure time lies
within one frame period after the move started; with the step placed at a random phase of the
frame clock its mean is half a period after. The move starts when the camera accepts the
command, which its VISCA ACK reports. So each trial gives ``arrival − t_ack − 1/(2·fps)``; the
median over the trials is the latency. The method ignores the exposure time (the mean is early
by half the exposure: 2 ms at 1/250 s) and the ACK's transit (≤ 3 ms at 9600 baud, ~0 on a
network). A camera acts on commands at field boundaries: when its frames are locked to the
fields, the step's phase is not random and a reading can be off by up to half a field (±8 ms at
60 Hz). Against the simulator it reads about −5 ms (±8 ms from run to run) where frames are
stamped exactly
(``sim.video = "direct"``), and the simulator's own capture delay plus encoding and transport
over HTTP (tests/test_latency.py).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.config import ConfigError, DffdConfig, load_config
from dffd.exitcodes import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from drivers.frames import FrameSource, FrameSourceError
from drivers.visca.camera import Camera, profile_for
from drivers.visca.errors import ViscaError
from drivers.visca.link import ViscaLink

_LOGGER = logging.getLogger(__name__)

DEFAULT_TRIALS = 15  # the median of 15 uniform phase errors (±17 ms at 30 fps) is good to ~3 ms
CHANGE_BLOCK_PX = 8  # block side for the change measure (averages the pixel noise 8×)
NOISE_FACTOR = 3.0  # "changed" = above this × the largest change between frames at rest
CHANGE_THRESHOLD_DN = 0.5  # … and never below this
NOISE_FRAMES = 4  # frames at rest that give the noise floor
# Frames read after the step before giving up: a latency above 20 frames (0.7 s at 30 fps) is
# not a camera's.
MAX_FRAMES = 20
# Rest after each move before the noise floor: a focus move's Completion can come before the
# image stops changing (motor ringing, auto exposure); 0.3 s = 9 frames at 30 fps.
SETTLE_S = 0.3
# Camera initialisation (the D100 takes ~10 s from standby) and one focus move.
CAMERA_INIT_TIMEOUT_S = 30.0
FRAME_TIMEOUT_S = 2.0  # a frame must arrive within this (a stream stalls ≤ read_timeout_s)
# The pan step: 2° shifts the image by ~100 px at the reference zoom (and ~20 px at the wide
# end), at 20°/s the first frame after the start already shows it.
STEP_PAN_DEG = 2.0
STEP_SPEED_DEG_S = 20.0


class LatencyError(RuntimeError):
    """The image never changed after a pan step (nothing with an edge in view, …)."""


@dataclass(frozen=True, slots=True)
class LatencyResult:
    """The latency (median of the trials) and every trial's value, seconds."""

    latency_s: float
    trials_s: tuple[float, ...]

    @property
    def spread_s(self) -> float:
        """Largest minus smallest trial."""
        return max(self.trials_s) - min(self.trials_s)


async def measure_latency_s(
    camera: Camera, source: FrameSource, *, trials: int = DEFAULT_TRIALS, seed: int = 1
) -> LatencyResult:
    """Pan-step the camera ``trials`` times; the latency of ``source`` (stamped on arrival)."""
    rng = np.random.default_rng(seed)
    period = 1.0 / source.fps
    samples: list[float] = []
    pan0, tilt0 = await camera.pan_tilt_position()
    lo, hi = camera.profile.pan_range_deg
    # Step towards the side with room, and back.
    pans = (pan0, pan0 + STEP_PAN_DEG if pan0 + STEP_PAN_DEG <= hi else pan0 - STEP_PAN_DEG)
    if not lo <= pans[1] <= hi:
        raise LatencyError(f"no room for a {STEP_PAN_DEG}° pan step at pan {pan0:.1f}°")
    try:
        for trial in range(trials):
            threshold, prev = await _rest(source)
            # Place the step at a random phase of the frame clock (see the module docstring).
            await asyncio.sleep(float(rng.uniform(0.0, period)))
            handle = await camera.start_pan_tilt_absolute(
                pans[(trial + 1) % 2], tilt0, STEP_SPEED_DEG_S
            )
            await handle.acked()
            t_ack = time.monotonic()
            arrival = await _first_changed(source, prev, threshold, t_ack)
            await handle.completed()
            samples.append(arrival - t_ack - 0.5 * period)
            _LOGGER.info("latency trial %d: %.1f ms", trial + 1, samples[-1] * 1e3)
    finally:
        with contextlib.suppress(ViscaError):
            await camera.pan_tilt_absolute(pan0, tilt0, STEP_SPEED_DEG_S)
    return LatencyResult(statistics.median(samples), tuple(samples))


def run(args: argparse.Namespace) -> int:
    """``dffd calibrate --latency --config FILE``: print ``latency_s``; return the exit code."""
    if args.config is None:
        print(
            "dffd calibrate --latency: give --config FILE (the camera and video of FILE, as "
            "dffd run starts them; camera.driver = 'sim' with sim.video = 'http' for the "
            "simulator's network video)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"dffd calibrate: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        trials = args.trials if args.trials is not None else DEFAULT_TRIALS
        if trials < 1:
            print("dffd calibrate: --trials must be at least 1", file=sys.stderr)
            return EXIT_USAGE
        result = asyncio.run(measure_for_config(config, trials=trials))
    except (LatencyError, ViscaError, FrameSourceError, TimeoutError, OSError) as exc:
        print(f"dffd calibrate --latency: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    print(
        f"capture latency: {result.latency_s * 1e3:.1f} ms (median of {len(result.trials_s)} "
        f"pan steps, spread {result.spread_s * 1e3:.1f} ms)"
    )
    print(f"[capture]\nlatency_s = {max(0.0, result.latency_s):.3f}")
    return EXIT_OK


async def measure_for_config(config: DffdConfig, *, trials: int = DEFAULT_TRIALS) -> LatencyResult:
    """Start the camera and the video of ``config`` as the daemon does; measure the latency."""
    from dffd.daemon.startup import DaemonError, open_source, start_camera_transport

    cap = config.capture.model_copy(update={"latency_s": 0.0, "timestamps": "arrival"})
    cfg = config.model_copy(update={"capture": cap})
    async with contextlib.AsyncExitStack() as stack:
        try:
            port, _server, rig = await start_camera_transport(cfg, stack, None)
            link = ViscaLink(port, cfg.camera.baudrate)
            await stack.enter_async_context(link)
            camera = Camera(link, cfg.camera.address, profile_for(cfg.camera.model))
            async with asyncio.timeout(CAMERA_INIT_TIMEOUT_S):
                await camera.initialize()
            source, *_ = await open_source(cfg, rig, stack)
        except DaemonError as exc:
            raise LatencyError(str(exc)) from exc
        await source.start()
        stack.push_async_callback(source.close)
        return await measure_latency_s(camera, source, trials=trials)


# -- private helpers --------------------------------------------------------------------------
async def _next(source: FrameSource) -> tuple[npt.NDArray[np.float64], float]:
    async with asyncio.timeout(FRAME_TIMEOUT_S):
        frame = await source.next_frame()
    image = frame.image if frame.image.ndim == 2 else frame.image[..., 1]
    return _blocks(image), float(frame.t)


async def _rest(source: FrameSource) -> tuple[float, npt.NDArray[np.float64]]:
    """Wait SETTLE_S of frames; the change threshold and the last frame's blocks."""
    prev, t = await _next(source)
    end = t + SETTLE_S
    while t < end:
        prev, t = await _next(source)
    noise = 0.0
    for _ in range(NOISE_FRAMES):
        blocks, _t = await _next(source)
        noise = max(noise, float(np.abs(blocks - prev).max()))
        prev = blocks
    return max(CHANGE_THRESHOLD_DN, NOISE_FACTOR * noise), prev


async def _first_changed(
    source: FrameSource, prev: npt.NDArray[np.float64], threshold: float, after: float
) -> float:
    """Arrival time of the first frame delivered after ``after`` that differs from its previous."""
    for _ in range(MAX_FRAMES):
        blocks, arrival = await _next(source)
        if arrival >= after and float(np.abs(blocks - prev).max()) > threshold:
            return arrival
        prev = blocks
    raise LatencyError(
        f"the image never changed within {MAX_FRAMES} frames of a pan step (threshold "
        f"{threshold:.2f} DN): put a high-contrast target in view and check that the camera "
        "pans"
    )


def _blocks(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
    b = CHANGE_BLOCK_PX
    h, w = image.shape[0] // b * b, image.shape[1] // b * b
    cropped = image[:h, :w].astype(np.float64)
    means: npt.NDArray[np.float64] = cropped.reshape(h // b, b, w // b, b).mean(axis=(1, 3))
    return means


__all__ = [
    "LatencyError",
    "LatencyResult",
    "measure_for_config",
    "measure_latency_s",
    "run",
]
