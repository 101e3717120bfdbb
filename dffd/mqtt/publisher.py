"""The MQTT client task: publishes payloads, survives broker outages, serves ``…/cmd``.

docs/design.md §7. One :class:`Publisher` per daemon. The daemon hands it payload models with
:meth:`Publisher.publish` (never blocks: a bounded queue, drop-oldest with a counter) and runs
:meth:`Publisher.run` in its TaskGroup (or uses ``async with Publisher(...)``). The client

- sets a retained ``offline`` Status as its last will and publishes a retained ``online`` Status
  on every connect;
- reconnects with capped exponential backoff;
- keeps estimates and measurements published while the broker is down in a bounded backlog
  (drop-oldest, counted) and replays them on reconnect with ``"replayed": true``;
- validates commands on ``…/cmd`` and answers each on ``…/cmd/reply`` (a bad command gets
  ``ok: false`` and a clear error, never an exception);
- on :meth:`stop`, flushes its queue, publishes a retained ``offline`` Status and disconnects.

Everything here runs on the event loop; from another thread use :meth:`publish_threadsafe`.

A command's parsing, validation, handler and reply are :mod:`dffd.mqtt.commands`; the settings
and the counters :mod:`dffd.mqtt.publisher_types`. :class:`Publisher` is one class of ~520 lines
kept whole: its connection loop, outbox, backlog, QoS 0 write path and command loop share the
one client of the current connection, the order of the messages between outbox, paho's queue and
backlog, and the counters; split, each part would reach into the others' state.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import aiomqtt
from paho.mqtt.client import MQTT_ERR_SUCCESS, MQTTMessageInfo

from dffd import __version__
from dffd.mqtt.commands import CommandHandler, execute_command
from dffd.mqtt.models import (
    Availability,
    CommandReply,
    Estimate,
    Measurement,
    MqttHealth,
    Status,
    Truth,
    wall_time,
)
from dffd.mqtt.publisher_types import PublisherSettings, PublisherStats
from dffd.mqtt.topics import TopicKind, Topics, qos, retained

__all__ = [
    "FLUSH_TIMEOUT_S",
    "PUBLISH_TIMEOUT_S",
    "Publisher",
]

_LOGGER = logging.getLogger(__name__)

# PUBACK of a QoS 1 publish (status, replies): same order as the connect round trip
# (publisher_types.CONNECT_TIMEOUT_S).
PUBLISH_TIMEOUT_S = 5.0
# Draining the publish queue on stop: the queue holds at most queue_max small messages, which a
# connected client writes in well under a second; systemd's TimeoutStopSec leaves room for 3 s.
FLUSH_TIMEOUT_S = 3.0
# Whole graceful stop (flush + offline status + DISCONNECT) before the task is cancelled.
STOP_TIMEOUT_S = FLUSH_TIMEOUT_S + PUBLISH_TIMEOUT_S
# Replay yields to the event loop after this many messages so a long backlog never stalls it.
_REPLAY_BATCH = 100
# QoS 0 messages handed to the MQTT client and not yet written to its socket, at most (~0.5 s of
# estimates and truth at 30 fps); past it the sender waits for the oldest, so the client's own
# queue stays bounded while the broker does not read.
QOS0_UNSENT_MAX = 32
# Poll period of that wait (it only happens while the socket does not drain).
QOS0_DRAIN_POLL_S = 0.005

Publishable = Estimate | Measurement | Status | Truth


@dataclass(frozen=True, slots=True)
class _Outgoing:
    kind: TopicKind
    payload: Publishable
    data: bytes | None = None  # the payload's JSON when the caller serialised it already


class Publisher:
    """The MQTT client of one camera; see the module docstring."""

    def __init__(
        self,
        settings: PublisherSettings,
        topics: Topics,
        *,
        on_command: CommandHandler | None = None,
        version: str = __version__,
    ) -> None:
        self.settings = settings
        self.topics = topics
        self._on_command = on_command
        self._version = version
        self._outbox: asyncio.Queue[_Outgoing] = asyncio.Queue(settings.queue_max_messages)
        self._sender_busy = False  # the sender task holds a message taken from the outbox
        self._backlog: deque[_Outgoing] = deque()
        # QoS 0 messages written through the paho client, until its socket took them.
        self._unsent: deque[tuple[MQTTMessageInfo, _Outgoing]] = deque()
        self._latest_status: Status | None = None
        self._client: aiomqtt.Client | None = None  # set only while connected and replayed
        self._up = asyncio.Event()
        self._down = asyncio.Event()
        self._down.set()
        self._stopping = asyncio.Event()
        self._done = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._counts = dict.fromkeys(
            (
                "connects", "connect_failures", "published", "replayed", "backlog_dropped",
                "queue_dropped", "offline_dropped", "commands", "commands_failed",
            ),
            0,
        )  # fmt: skip

    # -- lifecycle --------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        """Start :meth:`run` in a task owned by this object."""
        self._task = asyncio.create_task(self.run(), name="mqtt-publisher")
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Graceful :meth:`stop`; the task is cancelled if that overruns its time."""
        await self.stop()

    async def run(self) -> None:
        """Connect, publish, serve commands and reconnect until :meth:`stop` is called."""
        self._loop = asyncio.get_running_loop()
        self._done.clear()
        try:
            async with asyncio.TaskGroup() as group:
                sender = group.create_task(self._send_loop(), name="mqtt-send")
                await self._connection_loop()
                sender.cancel()
        finally:
            self._set_connected(None)
            if self._backlog:
                _LOGGER.warning(
                    "MQTT stopped with %d undelivered messages (they are in the JSONL log)",
                    len(self._backlog),
                )
            self._done.set()

    def request_stop(self) -> None:
        """Ask :meth:`run` to flush, publish ``offline`` and return (does not wait)."""
        self._stopping.set()

    async def stop(self, grace_s: float = STOP_TIMEOUT_S) -> None:
        """Request stop and wait for :meth:`run` to finish (cancel it after ``grace_s``)."""
        self.request_stop()
        if self._loop is None and self._task is None:
            return
        try:
            async with asyncio.timeout(grace_s):
                await self._done.wait()
        except TimeoutError:
            _LOGGER.warning("MQTT client did not stop within %.1f s; cancelling it", grace_s)
            if self._task is not None:
                self._task.cancel()
        if self._task is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    async def wait_connected(self) -> None:
        """Wait until connected and the backlog is replayed (wrap in asyncio.timeout)."""
        await self._up.wait()

    async def wait_disconnected(self) -> None:
        """Wait until not connected (wrap in asyncio.timeout)."""
        await self._down.wait()

    # -- publishing (never blocks) ----------------------------------------------------------

    def publish(self, payload: Publishable, data: bytes | None = None) -> None:
        """Send ``payload`` on its topic: a QoS 0 message goes to the socket in this call while
        connected (:meth:`_send_now`); anything else is queued, dropping the oldest queued
        message if the queue is full.

        Call on the event loop thread; ``data``: the payload's JSON if the caller has it already
        (``payload.to_json()``). A Status is also remembered and re-sent (as ``online``) on
        every reconnect.
        """
        kind = _kind_of(payload)
        if isinstance(payload, Status):
            self._latest_status = payload
        elif not self._sender_busy and self._outbox.empty() and self._send_now(kind, payload, data):
            return
        if self._outbox.full():
            self._outbox.get_nowait()
            self._outbox.task_done()
            self._counts["queue_dropped"] += 1
        self._outbox.put_nowait(_Outgoing(kind, payload, data))

    def publish_threadsafe(self, payload: Publishable, data: bytes | None = None) -> None:
        """:meth:`publish` from another thread (e.g. the estimator thread)."""
        if self._loop is None:
            msg = "Publisher.run() has not started; cannot publish from another thread yet"
            raise RuntimeError(msg)
        self._loop.call_soon_threadsafe(self.publish, payload, data)

    @property
    def connected(self) -> bool:
        """True while connected to the broker and done replaying the backlog."""
        return self._client is not None

    def stats(self) -> PublisherStats:
        """A snapshot of the counters."""
        return PublisherStats(connected=self.connected, backlog=len(self._backlog), **self._counts)

    def health(self, *, connected: bool | None = None) -> MqttHealth:
        """The ``mqtt`` block of a Status payload (``connected`` overrides the current flag)."""
        return MqttHealth(
            connected=self.connected if connected is None else connected,
            reconnects=max(0, self._counts["connects"] - 1),
            published=self._counts["published"],
            replayed=self._counts["replayed"],
            backlog=len(self._backlog),
        )

    def status_payload(
        self,
        availability: Availability,
        message: str | None = None,
        *,
        connected: bool | None = None,
    ) -> Status:
        """The latest Status with ``availability`` (a minimal one if none was published);
        ``connected`` overrides the ``mqtt.connected`` flag (see :meth:`health`)."""
        now_wall, now_mono = wall_time(), time.monotonic()
        health = self.health(connected=connected)
        if self._latest_status is None:
            return Status(
                availability=availability,
                t=now_wall,
                t_mono=now_mono,
                camera=self.topics.camera,
                version=self._version,
                mqtt=health,
                message=message,
            )
        update: dict[str, Any] = {
            "availability": availability,
            "t": now_wall,
            "t_mono": now_mono,
            "mqtt": health,
        }
        if availability == "offline":
            update |= {"state": None, "message": message}
        return self._latest_status.model_copy(update=update)

    # -- connection -------------------------------------------------------------------------

    async def _connection_loop(self) -> None:
        backoff = self.settings.reconnect_min_s
        failures = 0
        while not self._stopping.is_set():
            client = self._make_client()
            entered = False
            try:
                async with client:
                    entered = True
                    self._counts["connects"] += 1
                    failures = 0
                    backoff = self.settings.reconnect_min_s
                    _LOGGER.info("MQTT connected to %s:%d", self.settings.host, self.settings.port)
                    await self._on_connect(client)
                    await self._serve(client)
                    if self._stopping.is_set():
                        await self._shutdown(client)
            except aiomqtt.MqttError as exc:
                if not entered:
                    self._counts["connect_failures"] += 1
                failures += 1
                log = _LOGGER.warning if failures == 1 else _LOGGER.debug
                log(
                    "MQTT broker %s:%d unavailable (%s); retrying in %.1f s",
                    self.settings.host, self.settings.port, exc, backoff,
                )  # fmt: skip
            finally:
                self._set_connected(None)
                self._keep_unsent()
            if self._stopping.is_set():
                break
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(backoff):
                    await self._stopping.wait()
            backoff = min(backoff * 2, self.settings.reconnect_max_s)

    def _make_client(self) -> aiomqtt.Client:
        s = self.settings
        tls = None
        if s.tls:
            tls = aiomqtt.TLSParameters(
                ca_certs=str(s.ca_file) if s.ca_file else None,
                certfile=str(s.certfile) if s.certfile else None,
                keyfile=str(s.keyfile) if s.keyfile else None,
                cert_reqs=ssl.CERT_REQUIRED,
            )
        will = self.status_payload("offline", "connection lost (last will)")
        return aiomqtt.Client(
            s.host,
            s.port,
            username=s.username,
            password=s.password,
            will=aiomqtt.Will(
                self.topics.status, will.to_json(), qos=qos("status"), retain=retained("status")
            ),
            keepalive=s.keepalive_s,
            tls_params=tls,
            # Also the bound on a connection the broker drops before CONNACK (plain MQTT to a TLS
            # port): aiomqtt only notices that when this expires.
            timeout=s.connect_timeout_s,
            logger=_LOGGER.getChild("paho"),
            # Small messages at frame rate: without TCP_NODELAY, Nagle + the broker's delayed
            # ACK hold each write up to ~40 ms (measured 80 ms command round trips).
            socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),),
        )

    async def _on_connect(self, client: aiomqtt.Client) -> None:
        """Online status, command subscription, backlog replay — then open for live traffic."""
        # Sent over this connection, so it says connected (the flag is set only after replay).
        online = self.status_payload("online", connected=True)
        await client.publish(
            self.topics.status,
            online.to_json(),
            qos=qos("status"),
            retain=retained("status"),
            timeout=PUBLISH_TIMEOUT_S,
        )
        await client.subscribe(self.topics.cmd, qos=qos("cmd"), timeout=PUBLISH_TIMEOUT_S)
        # New messages keep going to the backlog until it is empty, so order is preserved.
        replayed = 0
        while self._backlog:
            item = self._backlog.popleft()
            try:
                await self._send(client, _replayed(item))
            except aiomqtt.MqttError:
                self._backlog.appendleft(item)
                raise
            replayed += 1
            self._counts["replayed"] += 1
            if replayed % _REPLAY_BATCH == 0:
                await asyncio.sleep(0)
        if replayed:
            _LOGGER.info("MQTT replayed %d messages from the outage backlog", replayed)
        self._write_through(client)
        self._set_connected(client)

    async def _serve(self, client: aiomqtt.Client) -> None:
        """Handle commands until the connection drops (MqttError) or stop is requested."""
        commands = asyncio.create_task(self._command_loop(client), name="mqtt-commands")
        stopping = asyncio.create_task(self._stopping.wait(), name="mqtt-stop-wait")
        try:
            await asyncio.wait((commands, stopping), return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (commands, stopping):
                task.cancel()
            await asyncio.gather(commands, stopping, return_exceptions=True)
        if commands.done() and not commands.cancelled() and commands.exception() is not None:
            raise commands.exception()  # type: ignore[misc]

    async def _shutdown(self, client: aiomqtt.Client) -> None:
        try:
            async with asyncio.timeout(FLUSH_TIMEOUT_S):
                await self._outbox.join()
        except TimeoutError:
            _LOGGER.warning(
                "MQTT flush incomplete after %.1f s; %d messages not sent",
                FLUSH_TIMEOUT_S, self._outbox.qsize(),
            )  # fmt: skip
        self._set_connected(None)
        offline = self.status_payload("offline", "stopped")
        await client.publish(
            self.topics.status,
            offline.to_json(),
            qos=qos("status"),
            retain=retained("status"),
            timeout=PUBLISH_TIMEOUT_S,
        )
        _LOGGER.info("MQTT published offline status; disconnecting")

    def _set_connected(self, client: aiomqtt.Client | None) -> None:
        self._client = client
        if client is None:
            self._up.clear()
            self._down.set()
        else:
            self._down.clear()
            self._up.set()

    # -- sending ----------------------------------------------------------------------------

    async def _send_loop(self) -> None:
        while True:
            item = await self._outbox.get()
            self._sender_busy = True  # publish() queues behind it (see _send_now)
            try:
                client = self._client
                if client is None:
                    self._keep_for_later(item)
                    continue
                try:
                    await self._send(client, item)
                except aiomqtt.MqttError as exc:
                    _LOGGER.debug("MQTT publish failed (%s); keeping the message", exc)
                    self._keep_for_later(item)
            finally:
                self._sender_busy = False
                self._outbox.task_done()

    async def _send(self, client: aiomqtt.Client, item: _Outgoing) -> None:
        payload = item.payload
        data = item.data
        if isinstance(payload, Status):
            # A status is built before it is sent (possibly before this connection existed):
            # its mqtt block says what holds as it goes out over this connection.
            payload = payload.model_copy(update={"mqtt": self.health(connected=True)})
            data = None
        topic = self.topics.name(item.kind)
        if data is None:
            data = payload.to_json()
        if qos(item.kind) == 0:
            await self._send_qos0(client, topic, data, item)
        else:
            await client.publish(
                topic, data, qos=qos(item.kind), retain=retained(item.kind),
                timeout=PUBLISH_TIMEOUT_S,
            )  # fmt: skip
        self._counts["published"] += 1

    async def _send_qos0(
        self, client: aiomqtt.Client, topic: str, data: bytes, item: _Outgoing
    ) -> None:
        """Hand a QoS 0 message to the paho client under aiomqtt without awaiting its write.

        ``aiomqtt.Client.publish`` makes the same paho call and then waits, with a task and an
        event per message, until paho has written it to the socket: ~210 µs of event-loop CPU
        per message against ~40-70 µs for the paho call alone (measured, loopback mosquitto),
        and two more loop iterations before the next message goes. QoS 0 has no
        acknowledgement to wait for; the socket write still happens on the loop (aiomqtt's
        writer callback). At most :data:`QOS0_UNSENT_MAX` messages wait in paho's queue; those
        still unwritten when the connection drops go to the backlog (:meth:`_keep_unsent`).
        """
        unsent = self._unsent
        while unsent and unsent[0][0].is_published():
            unsent.popleft()
        if len(unsent) >= QOS0_UNSENT_MAX:
            try:
                async with asyncio.timeout(PUBLISH_TIMEOUT_S):
                    # paho sets the flag in the loop's own socket-writer callback and offers no
                    # awaitable for it; this wait only happens while the socket does not drain.
                    while not unsent[0][0].is_published():  # noqa: ASYNC110
                        await asyncio.sleep(QOS0_DRAIN_POLL_S)
            except TimeoutError:
                raise aiomqtt.MqttError("MQTT socket did not drain; publish timed out") from None
            unsent.popleft()
        # aiomqtt keeps the paho client in `_client`; its own publish() calls exactly this. A
        # future aiomqtt without it gets the plain (slower) publish.
        paho = getattr(client, "_client", None)
        if paho is None:
            await client.publish(
                topic, data, qos=0, retain=retained(item.kind), timeout=PUBLISH_TIMEOUT_S
            )
            return
        info = paho.publish(topic, data, 0, retained(item.kind))
        if info.rc != MQTT_ERR_SUCCESS:
            raise aiomqtt.MqttCodeError(info.rc, "Could not publish message")
        if not info.is_published():
            unsent.append((info, item))

    def _send_now(self, kind: TopicKind, payload: Publishable, data: bytes | None) -> bool:
        """Write a QoS 0 message to the socket now, from :meth:`publish`; False: queue it.

        Only while connected, with nothing queued before it or held by the sender task (order
        is kept) and paho's queue below :data:`QOS0_UNSENT_MAX`: then the message is serialised
        and handed to paho here, and the socket write happens in the same call
        (:meth:`_write_through`), without the outbox, the sender task's wake-up and aiomqtt's
        writer registration (two loop iterations and three syscalls per message). Anything else
        takes the queued path.
        """
        client = self._client
        paho = getattr(client, "_client", None)
        if paho is None or qos(kind) != 0:
            return False
        unsent = self._unsent
        while unsent and unsent[0][0].is_published():
            unsent.popleft()
        if len(unsent) >= QOS0_UNSENT_MAX:
            return False
        item = _Outgoing(kind, payload, data)
        info = paho.publish(
            self.topics.name(kind), data if data is not None else payload.to_json(), 0,
            retained(kind),
        )  # fmt: skip
        if info.rc != MQTT_ERR_SUCCESS:
            # The connection is going down; the sender's path keeps the message for later.
            return False
        if not info.is_published():
            unsent.append((info, item))
        self._counts["published"] += 1
        return True

    def _write_through(self, client: aiomqtt.Client) -> None:
        """Let paho write on the loop thread at once when a message is queued on it.

        aiomqtt answers paho's "socket has data to write" with ``call_soon_threadsafe(
        add_writer)``: a self-pipe write, an epoll registration and two loop iterations before
        the ``send`` — per message. On the loop thread this hook calls paho's ``loop_write``
        directly instead; only when the socket does not take everything (EAGAIN) is aiomqtt's
        writer registered, as before. Calls from other threads (paho's connect, in aiomqtt's
        executor) keep aiomqtt's path.
        """
        paho = getattr(client, "_client", None)
        loop = self._loop
        if paho is None or loop is None:
            return
        original = paho.on_socket_register_write
        if original is None:
            return
        loop_thread = threading.get_ident()

        def register_write(mqttc: Any, userdata: Any, sock: Any) -> None:
            if threading.get_ident() != loop_thread:
                original(mqttc, userdata, sock)
                return
            try:
                mqttc.loop_write()
            except Exception:  # noqa: BLE001 - aiomqtt's writer callback reports it (below)
                original(mqttc, userdata, sock)
                return
            if mqttc.want_write():  # the socket is full: wait for it on the loop, as aiomqtt does
                original(mqttc, userdata, sock)

        paho.on_socket_register_write = register_write

    def _keep_unsent(self) -> None:
        """After a connection ends: QoS 0 messages paho never wrote go back, oldest first."""
        lost = [item for info, item in self._unsent if not info.is_published()]
        self._unsent.clear()
        kept = [item for item in lost if item.kind in ("estimate", "measurement")]
        self._counts["offline_dropped"] += len(lost) - len(kept)
        limit = self.settings.backlog_max_messages
        room = max(0, limit - len(self._backlog))
        self._counts["backlog_dropped"] += max(0, len(kept) - room)
        # Older than anything that went to the backlog since: in front of it.
        self._backlog.extendleft(reversed(kept[len(kept) - room :] if room else []))

    def _keep_for_later(self, item: _Outgoing) -> None:
        if item.kind not in ("estimate", "measurement"):
            # Truth is only useful live; the latest status is re-sent on reconnect.
            self._counts["offline_dropped"] += 1
            return
        limit = self.settings.backlog_max_messages
        if limit == 0:
            self._counts["backlog_dropped"] += 1
            return
        if len(self._backlog) >= limit:
            self._backlog.popleft()
            self._counts["backlog_dropped"] += 1
        self._backlog.append(item)

    # -- commands ---------------------------------------------------------------------------

    async def _command_loop(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            if not message.topic.matches(self.topics.cmd):
                continue
            reply = await self._execute(message.payload)
            self._counts["commands"] += 1
            if not reply.ok:
                self._counts["commands_failed"] += 1
            try:
                await client.publish(
                    self.topics.cmd_reply,
                    reply.to_json(),
                    qos=qos("cmd_reply"),
                    retain=retained("cmd_reply"),
                    timeout=PUBLISH_TIMEOUT_S,
                )
            except aiomqtt.MqttError as exc:
                _LOGGER.warning("MQTT could not send the reply to command %r: %s", reply.id, exc)

    async def execute(self, payload: object) -> CommandReply:
        """Run one command as if it arrived on ``…/cmd`` (the web dashboard's path); the reply."""
        return await self._execute(payload)

    async def _execute(self, payload: object) -> CommandReply:
        """Parse, validate and run one command; every failure becomes an ``ok: false`` reply."""
        return await execute_command(payload, self._on_command, self._version)


def _kind_of(payload: Publishable) -> TopicKind:
    if isinstance(payload, Estimate):
        return "estimate"
    if isinstance(payload, Measurement):
        return "measurement"
    if isinstance(payload, Status):
        return "status"
    return "sim_truth"


def _replayed(item: _Outgoing) -> _Outgoing:
    payload = item.payload
    if isinstance(payload, Estimate | Measurement):
        return _Outgoing(item.kind, payload.model_copy(update={"replayed": True}))
    return item
