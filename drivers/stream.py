"""Network video (RTSP, HTTP MJPEG) and video files through OpenCV's FFmpeg backend.

A reader thread blocks in ``VideoCapture.read()`` and hands frames to the event loop through the
same bounded drop-oldest buffer as the V4L2 source (:class:`drivers.capture.FrameHandoff`). Each
frame's mid-exposure time comes from :class:`drivers.exposure.ExposureClock`: the stream's
timestamps where they behave like a clock, otherwise arrival minus the measured latency.

FFmpeg is given open and read timeouts (``CAP_PROP_OPEN_TIMEOUT_MSEC``,
``CAP_PROP_READ_TIMEOUT_MSEC``), so a camera that stops sending makes ``read()`` fail instead of
hanging; the stream is then released and reopened with a capped exponential backoff, each loss
logged and counted (:attr:`StreamFrameSource.reconnects`, reported in the daemon's status). A
video file is played at its own frame rate (paced on its timestamps, as a live camera would
deliver it) and ends (:class:`drivers.capture.EndOfVideoError`).

Lab set-up
----------
* RTSP (Sony SRG/BRC, PTZOptics, BirdDog…): ``rtsp://USER:PASS@HOST:554/…`` (the path is in the
  camera's manual; often ``/video1`` or ``/1``). Prefer the camera's lowest-latency profile and a
  fixed frame rate; B-frames off if it offers that. FFmpeg's RTSP goes over UDP by default; set
  the environment variable ``OPENCV_FFMPEG_CAPTURE_OPTIONS="rtsp_transport;tcp"`` for TCP when
  the network loses packets (decoding artefacts cost more than the extra latency).
* HTTP MJPEG: ``http://HOST/…mjpg``. MJPEG streams carry no timestamps (frame times come from
  arrival; measure the latency).
* The latency is measured by ``dffd calibrate --latency`` and set as ``[capture] latency_s``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.capture import (
    OpenCVCapture,
    ThreadedFrameSource,
    VideoCaptureLike,
    backoff_delays,
)
from drivers.exposure import ExposureClock, TimestampMode
from drivers.frames import Frame

log = logging.getLogger(__name__)

# FFmpeg's own defaults are 30 s for both; a camera that has not answered in 5 s is down, and a
# stream silent for 2 s (60 frames at 30 fps) is lost — reconnecting beats waiting.
OPEN_TIMEOUT_S = 5.0
READ_TIMEOUT_S = 2.0
RECONNECT_INITIAL_S = 0.5  # first wait before reconnecting a lost stream
RECONNECT_MAX_S = 10.0  # backoff cap: a rebooted camera (~30 s) is picked up within 10 s of it
# Exposure times kept per frame index for exposure_time() (8 s at 30 fps).
KEPT_TIMES = 256
# A gap between consecutive frames longer than this many nominal periods counts the missing
# periods as dropped.
GAP_PERIODS = 1.5

StreamCaptureFactory = Callable[[str, Sequence[int]], VideoCaptureLike]


@dataclass(frozen=True, slots=True)
class StreamSettings:
    """What to open and how (mirrors ``[capture]`` with ``source = "stream"``)."""

    url: str  # rtsp://…, http://…, or a video file path
    fps: float = 30.0  # nominal rate, used until the stream reports its own
    gray: bool = True  # deliver H×W gray (the estimator's input) instead of BGR
    queue_frames: int = 2  # frames waiting for next_frame(); the oldest is dropped beyond
    latency_s: float = 0.0  # mid-exposure → read() return, measured by dffd calibrate --latency
    timestamps: TimestampMode = "auto"
    open_timeout_s: float = OPEN_TIMEOUT_S
    read_timeout_s: float = READ_TIMEOUT_S
    reconnect_initial_s: float = RECONNECT_INITIAL_S
    reconnect_max_s: float = RECONNECT_MAX_S

    @property
    def is_file(self) -> bool:
        """True when ``url`` names a local file (played once, paced on its timestamps)."""
        return "://" not in self.url and Path(self.url).is_file()


@dataclass(frozen=True, slots=True)
class StreamHealth:
    """The stream's state for the daemon's status."""

    url: str  # credentials removed
    connected: bool
    frames: int
    reconnects: int
    stream_timestamps: bool  # frame times from the stream's timestamps (else arrival − latency)
    latency_s: float


class StreamFrameSource(ThreadedFrameSource):
    """Frames from a network stream or a video file (a :class:`drivers.frames.FrameSource`)."""

    _noun = "stream"

    def __init__(
        self,
        settings: StreamSettings,
        *,
        capture_factory: StreamCaptureFactory | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(settings.queue_frames, clock, (0, 0), settings.fps)
        self.settings = settings
        self._factory: StreamCaptureFactory = capture_factory or _ffmpeg_capture
        self._stamps = ExposureClock(settings.timestamps, settings.latency_s)
        self._times: OrderedDict[int, float] = OrderedDict()
        self._times_lock = threading.Lock()
        self._frames = 0
        self._reconnects = 0
        self._connected = False

    @property
    def reconnects(self) -> int:
        """How many times the stream was lost and opened again."""
        return self._reconnects

    def health(self) -> StreamHealth:
        """Connection state and counters now."""
        return StreamHealth(
            url=redact(self.settings.url),
            connected=self._connected,
            frames=self._frames,
            reconnects=self._reconnects,
            stream_timestamps=self._stamps.using_stream or self.settings.is_file,
            latency_s=self.settings.latency_s,
        )

    def exposure_time(self, index: int) -> float | None:
        """The estimated mid-exposure time of a recent frame (None if unknown)."""
        with self._times_lock:
            return self._times.get(index)

    # -- reader thread -----------------------------------------------------------------------
    def _name(self) -> str:
        return self.settings.url

    def _open_error(self) -> str:
        return (
            f"cannot open video stream {redact(self.settings.url)!r} (refused, not found, or "
            f"no answer within {self.settings.open_timeout_s:g} s): check the URL (path and "
            "credentials are in the camera's manual), that the camera is reachable (ping, its "
            "web page) and that its stream is enabled; try it with `ffplay URL`"
        )

    def _open(self) -> VideoCaptureLike | None:
        s = self.settings
        params = [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, round(s.open_timeout_s * 1000),
            cv2.CAP_PROP_READ_TIMEOUT_MSEC, round(s.read_timeout_s * 1000),
        ]  # fmt: skip
        try:
            capture = self._factory(s.url, params)
        except cv2.error as exc:
            log.warning("opening %r failed: %s", redact(s.url), exc)
            return None
        if not capture.isOpened():
            capture.release()
            return None
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
        if width > 0 and height > 0:
            self._size = (width, height)
        # FFmpeg reports 25 fps for MJPEG over HTTP whatever the camera sends: a network
        # stream's rate is taken from the configuration; a file's from the file.
        if s.is_file and fps > 0:
            self._fps = fps
        self._connected = True
        log.info("opened %r: %dx%d", redact(s.url), *self._size)
        return capture

    def _read_loop(self, capture: VideoCaptureLike | None) -> None:
        s = self.settings
        index = 0
        last_arrival: float | None = None
        file_start: float | None = None
        delays = backoff_delays(s.reconnect_initial_s, s.reconnect_max_s)
        try:
            while not self._stop.is_set():
                if capture is None:
                    if self._stop.wait(next(delays)):
                        break
                    capture = self._open()
                    if capture is None:
                        log.debug("reconnecting %r failed; retrying", redact(s.url))
                        continue
                    self._reconnects += 1
                    log.warning(
                        "video stream %r reconnected (%d reconnects so far)",
                        redact(s.url), self._reconnects,
                    )  # fmt: skip
                    delays = backoff_delays(s.reconnect_initial_s, s.reconnect_max_s)
                    self._stamps.reset()
                    last_arrival = None
                ok, image = capture.read()
                if not ok or image is None:
                    if s.is_file:
                        self._ended = True
                        break
                    log.warning(
                        "video stream %r lost (no frame within %.1f s); reconnecting",
                        redact(s.url), s.read_timeout_s,
                    )  # fmt: skip
                    self._connected = False
                    capture.release()
                    capture = None
                    continue
                pts = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                if s.is_file:
                    # Deliver at the file's own rate, as a camera would: frame k at start + pts,
                    # which is its exposure time on our clock (the file's timeline is ours).
                    if file_start is None:
                        file_start = self._clock() - pts
                    if self._stop.wait(max(0.0, file_start + pts - self._clock())):
                        break
                arrival = self._clock()
                if last_arrival is not None and self._fps > 0:
                    periods = (arrival - last_arrival) * self._fps
                    if periods > GAP_PERIODS:
                        self._gap_dropped += max(0, round(periods) - 1)
                last_arrival = arrival
                t = file_start + pts if file_start is not None else self._stamps.stamp(arrival, pts)
                if s.gray and image.ndim == 3:
                    image = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
                self._remember(index, t)
                self._handoff.push(Frame(index, t, image))
                self._frames += 1
                index += 1
                self._notify()
        finally:
            self._connected = False
            if capture is not None:
                capture.release()
            self._notify()

    def _remember(self, index: int, t: float) -> None:
        with self._times_lock:
            self._times[index] = t
            while len(self._times) > KEPT_TIMES:
                self._times.popitem(last=False)


def redact(url: str) -> str:
    """``url`` without the password of a ``scheme://user:password@host`` form (for logs)."""
    scheme, sep, rest = url.partition("://")
    authority, slash, path = rest.partition("/")
    if not sep or "@" not in authority:
        return url
    userinfo, _, host = authority.rpartition("@")
    user = userinfo.split(":", 1)[0]
    return f"{scheme}://{user}:***@{host}{slash}{path}"


def _ffmpeg_capture(url: str, params: Sequence[int]) -> VideoCaptureLike:
    return OpenCVCapture(cv2.VideoCapture(url, cv2.CAP_FFMPEG, list(params)))
