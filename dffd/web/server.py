"""The dashboard's HTTP server (aiohttp): the page, live video, live data, commands, metrics.

Routes (all behind the token when one is set):

- ``GET /`` the page; ``GET /static/…`` its script and style (package data, works offline);
- ``GET /ws/video`` annotated JPEG frames over a WebSocket, ``GET /video.mjpeg`` the same as
  ``multipart/x-mixed-replace`` for players and ``curl``;
- ``GET /ws/events`` estimates, status and rejected bursts as JSON messages;
- ``GET /api/status`` one snapshot as JSON; ``POST /api/command`` one JSON command, answered with
  the same reply object ``…/cmd/reply`` carries (HTTP 200 when ``ok``, 400 when refused);
- ``GET /metrics`` Prometheus text format.

Safe by default: without a token the server binds loopback only (and answers only requests
addressed to a loopback name, against DNS rebinding); any other address needs a
bearer token (header ``Authorization: Bearer …``, or the cookie that ``/?token=…`` sets for a
browser). Commands must be ``application/json`` and same-origin, so another web page open in the
operator's browser cannot send them.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Final
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from dffd.web.interface import DashboardSource, Snapshot
from dffd.web.listen import WebConfigError, WebError, is_loopback, parse_listen
from dffd.web.metrics import CONTENT_TYPE, Metrics
from dffd.web.video import VIDEO_MAX_FPS, VideoBroadcaster

__all__ = [
    "DEFAULT_LISTEN",
    "DashboardServer",
    "WebConfigError",
    "WebError",
    "WebSettings",
    "is_loopback",
    "parse_listen",
    "read_token",
]

_LOGGER = logging.getLogger(__name__)

DEFAULT_LISTEN: Final = "127.0.0.1:8080"
# Period of the events stream: 5 Hz keeps the plots smooth without flooding a slow browser.
EVENTS_PERIOD_S: Final = 0.2
# Status messages on the events stream: the daemon refreshes its status once a second.
EVENTS_STATUS_PERIOD_S: Final = 0.5
# Estimates sent to a page when it connects: the plots' 60 s window at up to 30 Hz.
EVENTS_HISTORY_MAX: Final = 1800
# A command body is a small JSON object; anything larger is refused before parsing.
COMMAND_MAX_BYTES: Final = 4096
# Stopping the site: open WebSockets are closed; 2 s bounds a client that does not answer.
SHUTDOWN_TIMEOUT_S: Final = 2.0
# WebSocket keep-alive: a vanished browser is noticed within a few heartbeats.
WS_HEARTBEAT_S: Final = 10.0
TOKEN_COOKIE: Final = "dffd_token"  # noqa: S105 - the cookie's name, not a secret
_MJPEG_BOUNDARY: Final = "dffdframe"
_STATIC = resources.files("dffd.web") / "static"
_STATIC_TYPES: Final = {
    "app.js": "text/javascript",
    "style.css": "text/css",
    "index.html": "text/html",
}


@dataclass(frozen=True, slots=True)
class WebSettings:
    """Where to listen and the bearer token (None: loopback only, no token)."""

    host: str
    port: int
    token: str | None = None
    video_max_fps: float = VIDEO_MAX_FPS

    @classmethod
    def from_values(cls, listen: str, token_file: Path | None = None) -> WebSettings:
        """From ``[web] listen`` and ``token_file``; WebConfigError when unsafe or unreadable."""
        host, port = parse_listen(listen)
        token = read_token(token_file) if token_file is not None else None
        settings = cls(host, port, token)
        settings.check()
        return settings

    def check(self) -> None:
        """Refuse a non-loopback address without a token."""
        if self.token is None and not is_loopback(self.host):
            raise WebConfigError(
                f"web.listen = {self.host!r} is not a loopback address and web.token_file is "
                "not set: anyone on the network could command the camera. Set web.token_file "
                'to a file holding a secret token, or listen on "127.0.0.1:PORT"'
            )


def read_token(path: Path) -> str:
    """The token in ``path`` (surrounding white space stripped); raises WebConfigError."""
    try:
        token = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise WebConfigError(f"web.token_file {str(path)!r} cannot be read: {exc}") from exc
    if len(token) < 16:
        raise WebConfigError(
            f"web.token_file {str(path)!r} holds {len(token)} characters; use a secret of at "
            "least 16 (e.g. `openssl rand -hex 32 > FILE`)"
        )
    return token


class DashboardServer:
    """The dashboard of one daemon: ``async with`` it, or :meth:`start` / :meth:`stop`."""

    def __init__(
        self, settings: WebSettings, source: DashboardSource, metrics: Metrics | None = None
    ) -> None:
        settings.check()
        self.settings = settings
        self.source = source
        self.metrics = metrics if metrics is not None else Metrics(source.snapshot)
        self.video = VideoBroadcaster(source.latest_frame, max_fps=settings.video_max_fps)
        self._runner: web.AppRunner | None = None
        self._site: web.TCPSite | None = None
        self._video_task: asyncio.Task[None] | None = None
        self._sockets: set[web.WebSocketResponse] = set()
        self._streams: set[asyncio.Task[Any]] = set()  # MJPEG handlers, cancelled on stop
        self.port: int | None = None  # the bound port (differs from settings.port for 0)
        self.app = self._make_app()

    @property
    def url(self) -> str:
        """``http://host:port`` of the running server."""
        host = f"[{self.settings.host}]" if ":" in self.settings.host else self.settings.host
        return f"http://{host}:{self.port}"

    async def __aenter__(self) -> DashboardServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Bind and serve (raises WebError when the address cannot be bound)."""
        self._runner = web.AppRunner(self.app, access_log=None, shutdown_timeout=SHUTDOWN_TIMEOUT_S)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.settings.host, self.settings.port)
        try:
            await site.start()
        except OSError as exc:
            await self._runner.cleanup()
            self._runner = None
            raise WebError(
                f"web.listen {self.settings.host}:{self.settings.port} cannot be bound ({exc}); "
                "choose a free port or stop what uses it"
            ) from exc
        self._site = site
        server = getattr(site, "_server", None)
        sockets = getattr(server, "sockets", None) or []
        self.port = int(sockets[0].getsockname()[1]) if sockets else self.settings.port
        self._video_task = asyncio.create_task(self.video.run(), name="web-video")
        _LOGGER.info("dashboard at %s", self.url)

    async def stop(self) -> None:
        """Close every client and stop serving (idempotent)."""
        task, self._video_task = self._video_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for ws in list(self._sockets):
            with contextlib.suppress(Exception):
                await ws.close()
        for stream in list(self._streams):
            stream.cancel()
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()

    async def serve_forever(self) -> None:
        """Start, then serve until cancelled (for a TaskGroup)."""
        await self.start()
        try:
            await asyncio.Event().wait()
        finally:
            await asyncio.shield(self.stop())

    # -- app ------------------------------------------------------------------------------------
    def _make_app(self) -> web.Application:
        app = web.Application(middlewares=[self._auth], client_max_size=COMMAND_MAX_BYTES)
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/static/{name}", self._static),
                web.get("/ws/video", self._ws_video),
                web.get("/video.mjpeg", self._mjpeg),
                web.get("/ws/events", self._ws_events),
                web.get("/api/status", self._status),
                web.post("/api/command", self._command),
                web.get("/metrics", self._metrics),
            ]
        )
        return app

    @web.middleware
    async def _auth(
        self,
        request: web.Request,
        handler: Callable[[web.Request], Awaitable[web.StreamResponse]],
    ) -> web.StreamResponse:
        token = self.settings.token
        if token is None:
            if not _loopback_host(request.host):
                # Without a token only loopback may talk to us; a page whose DNS name was
                # rebound to 127.0.0.1 still sends its own name as Host.
                raise web.HTTPForbidden(
                    text=f"dffd dashboard: Host {request.host!r} refused; without web.token_file "
                    "the dashboard answers only to localhost / 127.0.0.1 / [::1]\n"
                )
            return await handler(request)
        if self._authorized(request, token):
            return await handler(request)
        given = request.query.get("token")
        if request.path == "/" and given is not None and hmac.compare_digest(given, token):
            # A browser cannot put a header on <img>, WebSocket or page loads: keep the token in
            # a same-site, script-invisible cookie and drop it from the address bar.
            response = web.HTTPFound("/")
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="Strict")
            raise response
        raise web.HTTPUnauthorized(
            text="dffd dashboard: a bearer token is required (header 'Authorization: Bearer "
            "TOKEN', or open /?token=TOKEN once in a browser)\n",
            headers={"WWW-Authenticate": 'Bearer realm="dffd"'},
        )

    @staticmethod
    def _authorized(request: web.Request, token: str) -> bool:
        header = request.headers.get("Authorization", "")
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(value.strip(), token):
            return True
        cookie = request.cookies.get(TOKEN_COOKIE)
        return cookie is not None and hmac.compare_digest(cookie, token)

    @staticmethod
    def _same_origin(request: web.Request) -> bool:
        """False when a browser says the request comes from another site's page."""
        origin = request.headers.get("Origin")
        if origin is None:
            return True  # not a browser cross-origin request (curl, Prometheus, MQTT tools)
        return urlsplit(origin).netloc == request.host

    # -- handlers -------------------------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.StreamResponse:
        return await self._static_file("index.html")

    async def _static(self, request: web.Request) -> web.StreamResponse:
        return await self._static_file(request.match_info["name"])

    async def _static_file(self, name: str) -> web.StreamResponse:
        content_type = _STATIC_TYPES.get(name)
        if content_type is None:
            raise web.HTTPNotFound()
        body = (_STATIC / name).read_bytes()
        return web.Response(
            body=body,
            content_type=content_type,
            charset="utf-8",
            headers={"Cache-Control": "no-cache"},
        )

    async def _ws_video(self, request: web.Request) -> web.StreamResponse:
        if not self._same_origin(request):
            raise web.HTTPForbidden(text="cross-origin WebSocket refused\n")
        ws = web.WebSocketResponse(heartbeat=WS_HEARTBEAT_S)
        await ws.prepare(request)
        self._sockets.add(ws)
        try:
            async with asyncio.TaskGroup() as group:
                # Reading is needed to notice the close; sending runs beside it.
                reader = group.create_task(self._drain(ws))
                async for jpeg in self.video.frames():
                    if ws.closed or reader.done():
                        break
                    await ws.send_bytes(jpeg)
                reader.cancel()
        except* (ConnectionError, RuntimeError) as exc:
            _LOGGER.debug("video viewer left: %s", exc.exceptions[0])
        finally:
            self._sockets.discard(ws)
        return ws

    async def _mjpeg(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": f"multipart/x-mixed-replace; boundary={_MJPEG_BOUNDARY}",
                "Cache-Control": "no-cache",
            }
        )
        await response.prepare(request)
        me = asyncio.current_task()
        if me is not None:
            self._streams.add(me)
        try:
            async for jpeg in self.video.frames():
                head = (
                    f"--{_MJPEG_BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(jpeg)}\r\n\r\n"
                ).encode()
                await response.write(head + jpeg + b"\r\n")
        except ConnectionError as exc:
            _LOGGER.debug("MJPEG viewer left: %s", exc)
        finally:
            if me is not None:
                self._streams.discard(me)
        return response

    async def _ws_events(self, request: web.Request) -> web.StreamResponse:
        if not self._same_origin(request):
            raise web.HTTPForbidden(text="cross-origin WebSocket refused\n")
        ws = web.WebSocketResponse(heartbeat=WS_HEARTBEAT_S)
        await ws.prepare(request)
        self._sockets.add(ws)
        try:
            async with asyncio.TaskGroup() as group:
                reader = group.create_task(self._drain(ws))
                await self._events(ws, reader)
                reader.cancel()
        except* (ConnectionError, RuntimeError) as exc:
            _LOGGER.debug("events viewer left: %s", exc.exceptions[0])
        finally:
            self._sockets.discard(ws)
        return ws

    async def _events(self, ws: web.WebSocketResponse, reader: asyncio.Task[None]) -> None:
        source = self.source
        points = list(source.estimates_after(-1))[-EVENTS_HISTORY_MAX:]
        last_seq = points[-1].estimate.seq if points else -1
        snap = source.snapshot()
        await ws.send_str(
            _dumps(
                {
                    "type": "hello",
                    "points": [p.to_json() for p in points],
                    "status": _snapshot_json(snap),
                    "rejections": _rejections_json(source),
                }
            )
        )
        loop = asyncio.get_running_loop()
        next_status = loop.time() + EVENTS_STATUS_PERIOD_S
        last_rejection: float | None = None
        while not ws.closed and not reader.done():
            await asyncio.sleep(EVENTS_PERIOD_S)
            new = source.estimates_after(last_seq)
            if new:
                last_seq = new[-1].estimate.seq
                await ws.send_str(
                    _dumps({"type": "estimates", "points": [p.to_json() for p in new]})
                )
            rejections = source.rejections()
            newest = rejections[-1].t_mono if rejections else None
            if newest != last_rejection:
                last_rejection = newest
                await ws.send_str(_dumps({"type": "rejections", "items": _rejections_json(source)}))
            if loop.time() >= next_status:
                next_status = loop.time() + EVENTS_STATUS_PERIOD_S
                status = _snapshot_json(source.snapshot())
                await ws.send_str(_dumps({"type": "status", "status": status}))

    @staticmethod
    async def _drain(ws: web.WebSocketResponse) -> None:
        async for msg in ws:
            if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                break

    async def _status(self, request: web.Request) -> web.StreamResponse:
        return web.json_response(_snapshot_json(self.source.snapshot()), dumps=_dumps)

    async def _command(self, request: web.Request) -> web.StreamResponse:
        if not self._same_origin(request):
            raise web.HTTPForbidden(text="commands from another site's page are refused\n")
        if request.content_type != "application/json":
            raise web.HTTPUnsupportedMediaType(
                text='send the command as JSON with "Content-Type: application/json"\n'
            )
        body = await request.read()
        reply = await self.source.execute(body)
        return web.Response(
            body=reply.to_json(),
            status=200 if reply.ok else 400,
            content_type="application/json",
        )

    async def _metrics(self, request: web.Request) -> web.StreamResponse:
        body = self.metrics.render()
        response = web.Response(body=body)
        response.headers["Content-Type"] = CONTENT_TYPE
        return response


def _loopback_host(host_header: str) -> bool:
    host = urlsplit(f"//{host_header}").hostname
    return host is not None and is_loopback(host)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def _snapshot_json(snap: Snapshot | None) -> dict[str, Any] | None:
    if snap is None:
        return None
    return {
        "status": snap.status.model_dump(mode="json", by_alias=True),
        "last_estimate_age_s": snap.last_estimate_age_s,
        "bursts_accepted": snap.bursts_accepted,
        "bursts_rejected": snap.bursts_rejected,
        "frame_size": list(snap.frame_size) if snap.frame_size else None,
        "message": snap.message,
    }


def _rejections_json(source: DashboardSource) -> list[dict[str, Any]]:
    return [
        {
            "burst": m.burst,
            "t": m.t,
            "t_mono": m.t_mono,
            "focus_counts": m.focus_counts,
            "reason": m.fit.reason or "rejected",
        }
        for m in source.rejections()
    ]
