"""The real frame source: OpenCV ``VideoCapture`` read in a dedicated thread.

A reader thread blocks in ``VideoCapture.read()`` and hands frames to the event loop through a
bounded drop-oldest buffer (the estimator wants the newest frame, never a backlog). Each frame is
stamped with ``time.monotonic()`` when ``read()`` returns, minus a configured capture latency, to
estimate its mid-exposure time. On a device, repeated read failures release and reopen it with a
capped exponential backoff; a video file simply ends (``next_frame`` then raises
:class:`EndOfVideoError`).

Lab set-up (Linux, V4L2)
------------------------
* Find the grabber: ``v4l2-ctl --list-devices`` (package ``v4l-utils``) or ``dffd devices``; use
  the stable path ``/dev/v4l/by-id/usb-…-video-index0`` rather than ``/dev/video0``, whose
  number depends on plug order. The service user must be in group ``video``.
* See what it can deliver: ``v4l2-ctl -d DEV --list-formats-ext``. Pick a format the device
  produces natively: ``YUYV`` (uncompressed; the analog-grabber case) or ``MJPG`` (compressed,
  adds decode time and JPEG artefacts on edges — avoid it for depth from focus when the bandwidth
  allows YUYV at 640×480 @ 30). Set ``[capture] fourcc``, ``width``, ``height``, ``fps``.
* OpenCV is opened with ``cv2.CAP_V4L2`` and the properties are set in the order V4L2 needs them:
  FOURCC, then size, then frame rate, then ``CAP_PROP_BUFFERSIZE = 1`` (one driver buffer, so a
  ``read()`` returns a fresh frame instead of one queued long ago). What the driver granted is
  read back and logged; a mismatch is a warning, not an error.
* Freeze the camera's own automation for repeatable focus costs: ``v4l2-ctl -d DEV -c
  exposure_auto=1`` style controls apply to USB cameras; an analog EVI camera's exposure is set
  over VISCA instead.
* The capture latency (exposure → ``read()``) is measured by ``dffd calibrate`` and configured as
  ``[capture] latency_frames``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from drivers.frames import Frame, FrameSourceError

log = logging.getLogger(__name__)

# Consecutive failed reads before a device is released and reopened: one failure can be a
# single corrupt frame from the grabber; three in a row (100 ms at 30 fps) is a lost device.
READ_FAILURES_BEFORE_REOPEN = 3
REOPEN_INITIAL_S = 0.5  # first wait before reopening a lost device
REOPEN_MAX_S = 10.0  # backoff cap: a replugged grabber is picked up within 10 s
# How long close() waits for the reader thread. A V4L2 read() blocked on a dead device returns
# after OpenCV's own select() timeout (10 s); the thread is a daemon, so it cannot hold up exit.
THREAD_JOIN_TIMEOUT_S = 2.0
# A gap between consecutive device frames longer than this many nominal periods counts the
# missing periods as dropped (the driver or the USB link lost them).
GAP_PERIODS = 1.5

Image = npt.NDArray[np.uint8]


class EndOfVideoError(FrameSourceError):
    """A video file has no more frames."""


class VideoCaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` used here (tests pass fakes)."""

    def isOpened(self) -> bool: ...  # noqa: N802 (OpenCV's name)

    def read(self) -> tuple[bool, Image | None]: ...

    def set(self, prop: int, value: float) -> bool: ...

    def get(self, prop: int) -> float: ...

    def release(self) -> None: ...


CaptureFactory = Callable[[str | int, int], VideoCaptureLike]


@dataclass(frozen=True, slots=True)
class CaptureSettings:
    """What to open and how (mirrors the ``[capture]`` config section)."""

    device: str | int  # /dev/video0, /dev/v4l/by-id/…, an index, or a video file
    width: int | None = 640
    height: int | None = 480
    fps: float | None = 30.0
    fourcc: str | None = None  # "YUYV", "MJPG", "GREY"…; None keeps the driver's choice
    buffer_size: int = 1
    gray: bool = True  # deliver H×W gray (the estimator's input) instead of BGR
    queue_frames: int = 2  # frames waiting for next_frame(); the oldest is dropped beyond
    latency_s: float = 0.0  # exposure mid-time = read time − latency_s
    reopen_initial_s: float = REOPEN_INITIAL_S
    reopen_max_s: float = REOPEN_MAX_S

    @property
    def is_file(self) -> bool:
        """True when ``device`` names a regular file (a recorded video)."""
        return isinstance(self.device, str) and Path(self.device).is_file()


def backoff_delays(initial_s: float, maximum_s: float) -> Iterator[float]:
    """Exponential backoff: initial, 2×, 4×, … capped at ``maximum_s``."""
    delay = initial_s
    while True:
        yield min(delay, maximum_s)
        delay = min(delay * 2.0, maximum_s)


class FrameHandoff:
    """Bounded thread → event-loop buffer that drops the oldest frame when full."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"handoff capacity must be at least 1, got {capacity}")
        self._frames: deque[Frame] = deque()
        self._capacity = capacity
        self._lock = threading.Lock()
        self.dropped = 0

    def push(self, frame: Frame) -> bool:
        """Add a frame; return True if the oldest one was dropped to make room."""
        with self._lock:
            dropped = len(self._frames) >= self._capacity
            if dropped:
                self._frames.popleft()
                self.dropped += 1
            self._frames.append(frame)
            return dropped

    def pop(self) -> Frame | None:
        """The oldest frame, or None."""
        with self._lock:
            return self._frames.popleft() if self._frames else None

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)


class ThreadedFrameSource:
    """The shell shared by the OpenCV sources: a reader thread, a :class:`FrameHandoff` and the
    async ``start``/``next_frame``/``close`` of :class:`drivers.frames.FrameSource`.

    A subclass opens its capture in :meth:`_open` (None if it cannot), reads it in
    :meth:`_read_loop` (pushing to ``self._handoff`` and calling :meth:`_notify` per frame;
    setting ``self._ended`` when a file ends) and names itself in :attr:`_noun` and
    :meth:`_open_error`.
    """

    _noun = "video"  # "capture", "stream": in the thread's name and in errors

    def __init__(
        self, queue_frames: int, clock: Callable[[], float], size: tuple[int, int], fps: float
    ) -> None:
        self._clock = clock
        self._handoff = FrameHandoff(queue_frames)
        self._size = size  # updated by _open from what the device or stream reports
        self._fps = fps
        self._gap_dropped = 0  # frames missing between consecutive reads
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = asyncio.Event()
        self._ended = False
        self._closed = False

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) the source delivers (the requested size, or (0, 0), before start)."""
        return self._size

    @property
    def fps(self) -> float:
        """The source's frame rate (the configured one when it does not say)."""
        return self._fps

    @property
    def dropped_frames(self) -> int:
        """Frames overwritten in the handoff plus frames missing between reads."""
        return self._handoff.dropped + self._gap_dropped

    async def start(self) -> None:
        """Open the source (raises :class:`FrameSourceError` if it cannot) and start reading."""
        if self._closed:
            raise FrameSourceError(f"{self._noun} source is closed; create a new one")
        if self._thread is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._ready = asyncio.Event()
        capture = await asyncio.to_thread(self._open)
        if capture is None:
            raise FrameSourceError(self._open_error())
        self._thread = threading.Thread(
            target=self._read_loop, args=(capture,), name=f"dffd-{self._noun}", daemon=True
        )
        self._thread.start()

    async def next_frame(self) -> Frame:
        """The oldest buffered frame (wrap in ``asyncio.timeout``)."""
        if self._thread is None:
            raise FrameSourceError(f"{self._noun} source not started; call start() first")
        while True:
            frame = self._handoff.pop()
            if frame is not None:
                return frame
            if self._ended:
                raise EndOfVideoError(f"end of video {self._name()!r}")
            if self._closed:
                raise FrameSourceError(f"{self._noun} source closed")
            self._ready.clear()
            frame = self._handoff.pop()  # a frame may have landed before clear()
            if frame is not None:
                return frame
            await self._ready.wait()

    async def close(self) -> None:
        """Stop the reader thread and release the capture; idempotent."""
        self._closed = True
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            await asyncio.to_thread(thread.join, THREAD_JOIN_TIMEOUT_S)
            if thread.is_alive():
                log.warning(
                    "%s thread still blocked in read() after %.1f s; leaving it to exit",
                    self._noun, THREAD_JOIN_TIMEOUT_S,
                )  # fmt: skip
        self._ready.set()

    # -- for subclasses ----------------------------------------------------------------------
    def _name(self) -> str:
        raise NotImplementedError

    def _open_error(self) -> str:
        raise NotImplementedError

    def _open(self) -> VideoCaptureLike | None:
        raise NotImplementedError

    def _read_loop(self, capture: VideoCaptureLike | None) -> None:
        raise NotImplementedError

    def _notify(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed between check and call
                loop.call_soon_threadsafe(self._ready.set)


class OpenCVFrameSource(ThreadedFrameSource):
    """Frames from a V4L2 device or a video file (a :class:`drivers.frames.FrameSource`)."""

    _noun = "capture"

    def __init__(
        self,
        settings: CaptureSettings,
        *,
        capture_factory: CaptureFactory | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        size = (settings.width or 0, settings.height or 0)
        super().__init__(settings.queue_frames, clock, size, settings.fps or 0.0)
        self.settings = settings
        self._factory: CaptureFactory = capture_factory or _opencv_capture
        self._reopens = 0

    @property
    def reopen_count(self) -> int:
        """How many times the device was released and reopened after failures."""
        return self._reopens

    # -- reader thread -----------------------------------------------------------------------
    def _name(self) -> str:
        return str(self.settings.device)

    def _open_error(self) -> str:
        return (
            f"cannot open video source {self.settings.device!r}: check that it exists "
            "(v4l2-ctl --list-devices, dffd devices), that this user is in group 'video', "
            "and that no other program holds it"
        )

    def _open(self) -> VideoCaptureLike | None:
        s = self.settings
        backend = cv2.CAP_ANY if s.is_file or sys.platform != "linux" else cv2.CAP_V4L2
        try:
            capture = self._factory(s.device, backend)
        except cv2.error as exc:
            log.warning("opening %r failed: %s", s.device, exc)
            return None
        if not capture.isOpened():
            capture.release()
            return None
        if not s.is_file:
            # V4L2 order: pixel format, then size, then rate; then a single driver buffer.
            if s.fourcc:
                capture.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*s.fourcc)))
            if s.width and s.height:
                capture.set(cv2.CAP_PROP_FRAME_WIDTH, float(s.width))
                capture.set(cv2.CAP_PROP_FRAME_HEIGHT, float(s.height))
            if s.fps:
                capture.set(cv2.CAP_PROP_FPS, float(s.fps))
            capture.set(cv2.CAP_PROP_BUFFERSIZE, float(s.buffer_size))
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
        if width > 0 and height > 0:
            if s.width and s.height and (width, height) != (s.width, s.height) and not s.is_file:
                log.warning(
                    "%r granted %dx%d instead of %dx%d", s.device, width, height, s.width, s.height
                )
            self._size = (width, height)
        if fps > 0:
            self._fps = fps
        log.info("opened %r: %dx%d @ %.2f fps", s.device, *self._size, self._fps)
        return capture

    def _read_loop(self, capture: VideoCaptureLike | None) -> None:
        s = self.settings
        index = 0
        failures = 0
        last_t: float | None = None
        delays = backoff_delays(s.reopen_initial_s, s.reopen_max_s)
        try:
            while not self._stop.is_set():
                if capture is None:
                    if self._stop.wait(next(delays)):
                        break
                    capture = self._open()
                    if capture is None:
                        log.debug("reopening %r failed; retrying", s.device)
                        continue
                    self._reopens += 1
                    log.warning("reopened %r", s.device)
                    delays = backoff_delays(s.reopen_initial_s, s.reopen_max_s)
                    last_t = None
                ok, image = capture.read()
                t = self._clock()
                if not ok or image is None:
                    if s.is_file:
                        self._ended = True
                        break
                    failures += 1
                    if failures >= READ_FAILURES_BEFORE_REOPEN:
                        log.warning("%d failed reads from %r; reopening", failures, s.device)
                        capture.release()
                        capture = None
                        failures = 0
                    continue
                failures = 0
                if not s.is_file and last_t is not None and self._fps > 0:
                    missing = round((t - last_t) * self._fps) - 1
                    if (t - last_t) * self._fps > GAP_PERIODS and missing > 0:
                        self._gap_dropped += missing
                last_t = t
                if s.gray and image.ndim == 3:
                    image = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
                self._handoff.push(Frame(index, t - s.latency_s, image))
                index += 1
                self._notify()
        finally:
            if capture is not None:
                capture.release()
            self._notify()


class OpenCVCapture:
    """An opened ``cv2.VideoCapture`` behind :class:`VideoCaptureLike` (any backend)."""

    def __init__(self, capture: cv2.VideoCapture) -> None:
        self._capture = capture

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return bool(self._capture.isOpened())

    def read(self) -> tuple[bool, Image | None]:
        ok, image = self._capture.read()
        if not ok or image is None:
            return False, None
        return True, np.asarray(image, dtype=np.uint8)

    def set(self, prop: int, value: float) -> bool:
        return bool(self._capture.set(prop, value))

    def get(self, prop: int) -> float:
        return float(self._capture.get(prop))

    def release(self) -> None:
        self._capture.release()


def _opencv_capture(device: str | int, backend: int) -> VideoCaptureLike:
    return OpenCVCapture(cv2.VideoCapture(device, backend))
