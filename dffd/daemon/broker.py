"""The embedded MQTT broker of the default run (``mqtt.url = "embedded"``): amqtt on loopback.

``async with EmbeddedBroker(port):`` starts an amqtt broker on ``127.0.0.1:port`` (anonymous,
loopback only, no persistence) and shuts it down on exit. A port that is already taken is a
:class:`BrokerStartError` saying what to do, raised before amqtt is touched.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
from types import TracebackType
from typing import Any, Self

from amqtt.broker import Broker

__all__ = ["BROKER_START_TIMEOUT_S", "BROKER_STOP_TIMEOUT_S", "BrokerStartError", "EmbeddedBroker"]

_LOGGER = logging.getLogger(__name__)

# amqtt binds its listener and fires its plugin start events in milliseconds on loopback.
BROKER_START_TIMEOUT_S = 5.0
# Shutdown disconnects every session and closes the listener; a handful of local clients.
BROKER_STOP_TIMEOUT_S = 5.0
LOOPBACK = "127.0.0.1"


class BrokerStartError(RuntimeError):
    """The embedded broker could not start; the message says why and what to do."""


class EmbeddedBroker:
    """An amqtt broker on ``host:port`` for the lifetime of an ``async with`` block."""

    def __init__(self, port: int, host: str = LOOPBACK) -> None:
        self.host = host
        self.port = port
        self._broker: Broker | None = None

    @property
    def url(self) -> str:
        """``mqtt://host:port`` of this broker."""
        return f"mqtt://{self.host}:{self.port}"

    async def start(self) -> None:
        """Bind and start serving (BrokerStartError if the port is taken or amqtt fails)."""
        _check_port_free(self.host, self.port)
        _quiet_amqtt_loggers()
        broker = Broker(_broker_config(self.host, self.port))
        try:
            async with asyncio.timeout(BROKER_START_TIMEOUT_S):
                await broker.start()
        except TimeoutError as exc:
            msg = f"embedded MQTT broker did not start within {BROKER_START_TIMEOUT_S} s"
            raise BrokerStartError(msg) from exc
        except Exception as exc:  # amqtt raises BrokerError wrapping anything
            raise BrokerStartError(
                f"embedded MQTT broker failed to start on {self.host}:{self.port}: {exc}; "
                "use an external broker (mqtt.url = mqtt://host:port) if this persists"
            ) from exc
        self._broker = broker
        _LOGGER.info("embedded MQTT broker listening on %s:%d", self.host, self.port)

    async def stop(self) -> None:
        """Disconnect every client and close the listener (idempotent)."""
        broker, self._broker = self._broker, None
        if broker is None:
            return
        try:
            async with asyncio.timeout(BROKER_STOP_TIMEOUT_S):
                await broker.shutdown()
        except TimeoutError:
            _LOGGER.warning("embedded MQTT broker did not shut down within %.1f s",
                            BROKER_STOP_TIMEOUT_S)  # fmt: skip
        _LOGGER.info("embedded MQTT broker stopped")

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()


def _broker_config(host: str, port: int) -> dict[str, Any]:
    return {
        "listeners": {"default": {"type": "tcp", "bind": f"{host}:{port}"}},
        # Only anonymous auth: no $SYS publisher, no per-packet logging plugins (they cost CPU
        # at frame rate and the broker is a private loopback service).
        "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
    }


def _check_port_free(host: str, port: int) -> None:
    """Raise BrokerStartError if something already listens on ``host:port``."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        # Same option amqtt's asyncio server uses, so TIME_WAIT leftovers do not count.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                msg = (
                    f"{host}:{port} is already in use (another MQTT broker such as mosquitto, "
                    "or another dffd?); stop it, or set mqtt.embedded_port "
                    "(DFFD_MQTT__EMBEDDED_PORT) to a free port, or use that broker with "
                    f"mqtt.url = mqtt://{host}:{port}"
                )
            else:
                msg = f"cannot listen on {host}:{port}: {exc.strerror}; choose another port"
            raise BrokerStartError(msg) from exc


def _quiet_amqtt_loggers() -> None:
    # amqtt logs every connection at INFO; keep that out of the service log unless asked for.
    for name in ("amqtt", "transitions"):
        logger = logging.getLogger(name)
        if logger.level == logging.NOTSET:
            logger.setLevel(logging.WARNING)
