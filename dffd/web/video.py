"""Annotated JPEG frames for any number of viewers, encoded only while someone watches.

One task polls the daemon's latest frame at most ``max_fps`` times a second, draws and encodes
it in one worker thread (never on the event loop, never on the estimator thread), and keeps only
the newest JPEG. Each viewer waits for a JPEG newer than the last it sent: a slow viewer skips
frames (drop-oldest) and never holds up the others or the daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Final

from dffd.web.interface import FrameView
from dffd.web.overlay import encode_jpeg

_LOGGER = logging.getLogger(__name__)

# Upper bound on the video rate: 10 fps shows motion well and costs ~1 ms of encoding per frame
# on one core (640×480), a few % of a core; the estimator needs the rest.
VIDEO_MAX_FPS: Final = 10.0
# A viewer waiting this long without a new frame gets a keep-alive chance (the loop re-checks
# that it is still wanted); the frame source may simply be idle.
VIEWER_WAIT_S: Final = 1.0


class VideoBroadcaster:
    """The latest annotated JPEG, produced on demand for the viewers of :meth:`frames`."""

    def __init__(
        self,
        latest_frame: Callable[[], FrameView | None],
        *,
        max_fps: float = VIDEO_MAX_FPS,
        encode: Callable[[FrameView], bytes] = encode_jpeg,
    ) -> None:
        if max_fps <= 0:
            raise ValueError(f"max_fps must be positive, got {max_fps}")
        self._latest_frame = latest_frame
        self._period_s = 1.0 / max_fps
        self._encode = encode
        self._viewers = 0
        self._wanted = asyncio.Event()
        self._idle = asyncio.Event()
        self._idle.set()
        self._new = asyncio.Event()
        self._jpeg: bytes | None = None
        self._seq = 0
        self._last_index: int | None = None
        self._executor: ThreadPoolExecutor | None = None
        self.encoded = 0  # frames encoded since start
        self.encode_failures = 0

    @property
    def viewers(self) -> int:
        """Viewers currently attached."""
        return self._viewers

    async def wait_no_viewers(self) -> None:
        """Return once no viewer is attached."""
        await self._idle.wait()

    async def run(self) -> None:
        """Produce frames while anyone watches; runs until cancelled."""
        loop = asyncio.get_running_loop()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dffd-web-jpeg")
        try:
            while True:
                if self._viewers == 0:
                    self._wanted.clear()
                    await self._wanted.wait()
                started = loop.time()
                view = self._latest_frame()
                if view is not None and view.index != self._last_index:
                    self._last_index = view.index
                    try:
                        jpeg = await loop.run_in_executor(self._executor, self._encode, view)
                    except Exception:  # one bad frame must not end the video
                        self.encode_failures += 1
                        level = logging.DEBUG if self.encode_failures > 1 else logging.WARNING
                        _LOGGER.log(level, "could not encode frame %d", view.index, exc_info=True)
                    else:
                        self._publish(jpeg)
                # Pacing, not waiting for an event: the rate bound is the point.
                await asyncio.sleep(max(0.0, self._period_s - (loop.time() - started)))
        finally:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    async def frames(self) -> AsyncIterator[bytes]:
        """Each newer JPEG as it comes (skipping any this viewer was too slow for)."""
        with self._attached():
            sent = 0
            while True:
                if self._jpeg is not None and self._seq != sent:
                    sent = self._seq
                    yield self._jpeg
                    continue
                new = self._new
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(VIEWER_WAIT_S):
                        await new.wait()

    def _publish(self, jpeg: bytes) -> None:
        self._jpeg = jpeg
        self._seq += 1
        self.encoded += 1
        new, self._new = self._new, asyncio.Event()
        new.set()

    @contextlib.contextmanager
    def _attached(self) -> Iterator[None]:
        self._viewers += 1
        self._wanted.set()
        self._idle.clear()
        try:
            yield
        finally:
            self._viewers -= 1
            if self._viewers == 0:
                self._idle.set()
