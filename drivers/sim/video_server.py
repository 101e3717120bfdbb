"""The simulated camera's video as MJPEG over HTTP, as network cameras serve it.

``GET /video.mjpg`` answers ``multipart/x-mixed-replace`` with one JPEG part per frame (the
format of IP cameras' "MJPEG over HTTP" and of ``ffmpeg -f mpjpeg``). Frames come from any
:class:`~drivers.frames.FrameSource` — the simulator's renderer — started when the first viewer
connects and rendered in real time; every viewer gets the newest frames through its own bounded
drop-oldest queue (a slow viewer loses frames, it never slows the camera). Like an MJPEG camera,
the parts carry no timestamps: a reader stamps frames on arrival.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from types import TracebackType
from typing import Self

import cv2
from aiohttp import web

from drivers.frames import FrameSource, FrameSourceError

logger = logging.getLogger(__name__)

PATH = "/video.mjpg"
BOUNDARY = "dffdsimframe"
# JPEG quality: high, so the focus cost sees the renderer's edges and not 8×8 block artefacts
# (at 95 a 640×480 gray frame is ~60 kB, 15 Mbit/s at 30 fps on loopback).
JPEG_QUALITY = 95
VIEWER_QUEUE_FRAMES = 2  # frames waiting per viewer; the oldest is dropped beyond
# A frame from the simulated renderer arrives every 33 ms; 2 s without one is a stalled source.
FRAME_TIMEOUT_S = 2.0
# Bound on closing viewers' connections at stop() (aiohttp's own default is 60 s).
SHUTDOWN_TIMEOUT_S = 1.0


class SimVideoServer:
    """Serve ``source`` as MJPEG over HTTP on ``host:port`` (0: any free port)."""

    def __init__(
        self,
        source: FrameSource,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        jpeg_quality: int = JPEG_QUALITY,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.jpeg_quality = jpeg_quality
        self.frames_sent = 0
        self._viewers: set[asyncio.Queue[bytes]] = set()
        self._runner: web.AppRunner | None = None
        self._pump_task: asyncio.Task[None] | None = None
        self._source_started = False

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    @property
    def url(self) -> str:
        """What a viewer opens: ``http://host:port/video.mjpg``."""
        return f"http://{self.host}:{self.port}{PATH}"

    async def start(self) -> None:
        """Listen (the source starts with the first viewer)."""
        app = web.Application()
        app.router.add_get(PATH, self._serve_viewer)
        self._runner = web.AppRunner(app, handle_signals=False, shutdown_timeout=SHUTDOWN_TIMEOUT_S)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        await site.start()
        if self.port == 0:
            self.port = self._runner.addresses[0][1]
        logger.info("sim camera: serving MJPEG video on %s", self.url)

    async def stop(self) -> None:
        """Close every viewer, stop listening, stop the source if this server started it."""
        task, self._pump_task = self._pump_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for queue in list(self._viewers):
            _put_newest(queue, b"")  # wakes the viewer, which ends its response
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._source_started:
            self._source_started = False
            await self.source.close()

    async def _serve_viewer(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                "Cache-Control": "no-cache, no-store",
            }
        )
        await response.prepare(request)
        queue: asyncio.Queue[bytes] = asyncio.Queue(VIEWER_QUEUE_FRAMES)
        self._viewers.add(queue)
        self._ensure_pump()
        try:
            while part := await queue.get():
                await response.write(part)
        except (ConnectionError, asyncio.CancelledError):
            logger.debug("sim video: viewer %s gone", request.remote)
        finally:
            self._viewers.discard(queue)
        return response

    def _ensure_pump(self) -> None:
        if self._pump_task is None or self._pump_task.done():
            self._pump_task = asyncio.create_task(self._pump(), name="sim-video-pump")

    async def _pump(self) -> None:
        if not self._source_started:
            await self.source.start()
            self._source_started = True
        while True:
            try:
                async with asyncio.timeout(FRAME_TIMEOUT_S):
                    frame = await self.source.next_frame()
            except (TimeoutError, FrameSourceError) as exc:
                logger.warning("sim video: the frame source stopped: %r", exc)
                return
            if not self._viewers:
                continue
            part = await asyncio.to_thread(self._encode, frame.image)
            for queue in list(self._viewers):
                _put_newest(queue, part)
            self.frames_sent += 1

    def _encode(self, image: object) -> bytes:
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])  # type: ignore[call-overload]
        if not ok:
            raise FrameSourceError("JPEG encoding of a simulated frame failed")
        data: bytes = jpeg.tobytes()
        head = (
            f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(data)}\r\n\r\n"
        ).encode("ascii")
        return head + data + b"\r\n"


def _put_newest(queue: asyncio.Queue[bytes], item: bytes) -> None:
    """Put ``item``, dropping the oldest queued one if the queue is full."""
    if queue.full():
        with contextlib.suppress(asyncio.QueueEmpty):
            queue.get_nowait()
    queue.put_nowait(item)
