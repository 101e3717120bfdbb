"""What the owner of a :class:`~dffd.mqtt.publisher.Publisher` hands it and reads back: its
settings (from ``[mqtt]``) and a snapshot of its counters."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dffd.config import MqttSection

__all__ = ["CONNECT_TIMEOUT_S", "PublisherSettings", "PublisherStats"]

# Connect + CONNACK: a loopback or LAN broker answers in milliseconds; 10 s (aiomqtt's default)
# covers a slow TLS handshake without stalling shutdown for long.
CONNECT_TIMEOUT_S = 10.0


@dataclass(frozen=True, slots=True)
class PublisherSettings:
    """Connection and buffering parameters (usually built with :meth:`from_config`)."""

    host: str
    port: int
    tls: bool = False
    username: str | None = None
    password: str | None = None
    ca_file: Path | None = None
    certfile: Path | None = None
    keyfile: Path | None = None
    keepalive_s: int = 30
    backlog_max_messages: int = 10_000
    queue_max_messages: int = 1_000
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0
    connect_timeout_s: float = CONNECT_TIMEOUT_S

    @classmethod
    def from_config(cls, config: MqttSection) -> PublisherSettings:
        """From ``[mqtt]``; reads the password file (raises ConfigError if unreadable)."""
        endpoint = config.endpoint
        return cls(
            host=endpoint.host,
            port=endpoint.port,
            tls=endpoint.tls,
            username=config.username,
            password=config.read_password(),
            ca_file=config.ca_file,
            certfile=config.certfile,
            keyfile=config.keyfile,
            keepalive_s=config.keepalive_s,
            backlog_max_messages=config.backlog_max_messages,
            queue_max_messages=config.queue_max_messages,
            reconnect_min_s=config.reconnect_min_s,
            reconnect_max_s=config.reconnect_max_s,
        )


@dataclass(frozen=True, slots=True)
class PublisherStats:
    """Counters since start (all monotonic except ``connected`` and ``backlog``)."""

    connected: bool
    connects: int  # successful connections
    connect_failures: int  # failed connection attempts
    published: int  # messages handed to the broker (incl. replayed)
    replayed: int  # backlog messages sent after a reconnect
    backlog: int  # messages waiting in the backlog now
    backlog_dropped: int  # oldest backlog messages dropped because the backlog was full
    queue_dropped: int  # oldest queued messages dropped because the queue was full
    offline_dropped: int  # truth/status messages not kept while offline (status is resent)
    commands: int  # command messages received
    commands_failed: int  # of which answered with ok=false
