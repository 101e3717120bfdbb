"""The camera port as one URL: which transport carries the VISCA bytes, and where to.

``[camera] port`` accepts

* ``serial:///dev/visca0?baud=9600`` or a bare path (``/dev/ttyUSB0``; any other pyserial URL such
  as ``loop://`` or ``socket://host:port`` also goes to pyserial): RS-232;
* ``visca-ip://192.168.0.100:52381`` (port 52381 if omitted): VISCA over IP, UDP;
* ``tcp://192.168.0.100:5678`` (port 5678 if omitted): raw VISCA over TCP (PTZOptics style).

:func:`parse_camera_url` is pure; a ValueError says what was wrong and what a valid URL is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal
from urllib.parse import parse_qs, urlsplit

VISCA_IP_DEFAULT_PORT = 52381  # Sony's VISCA-over-IP port
RAW_TCP_DEFAULT_PORT = 5678  # PTZOptics' raw VISCA TCP port

TransportKind = Literal["serial", "visca-ip", "tcp"]
EXAMPLES = "serial:///dev/visca0?baud=9600, /dev/ttyUSB0, visca-ip://host:52381, tcp://host:5678"


@dataclass(frozen=True, slots=True)
class CameraUrl:
    """A parsed camera port: the transport and its address."""

    transport: TransportKind
    target: str  # serial: what pyserial opens; network: the host
    port: int | None = None  # network port
    baudrate: int | None = None  # serial ``?baud=``; None: the configured baud rate


def parse_camera_url(url: str) -> CameraUrl:
    """Parse ``url`` (see the module doc); ValueError naming the problem and valid forms."""
    text = url.strip()
    if not text:
        raise ValueError(f"camera port is empty; use one of: {EXAMPLES}")
    scheme, sep, _ = text.partition("://")
    scheme = scheme.lower() if sep else ""
    if scheme == "serial":
        parts = urlsplit(text)
        path = parts.path
        if not path:
            raise ValueError(f"{url!r} names no device; e.g. serial:///dev/visca0?baud=9600")
        return CameraUrl("serial", path, baudrate=_baud(parts.query, url))
    if scheme in ("visca-ip", "tcp"):
        parts = urlsplit(text)
        if not parts.hostname:
            raise ValueError(f"{url!r} names no host; e.g. {scheme}://192.168.0.100")
        try:
            port = parts.port
        except ValueError as exc:
            raise ValueError(f"{url!r}: the port must be a number 1–65535") from exc
        if port is None:
            port = VISCA_IP_DEFAULT_PORT if scheme == "visca-ip" else RAW_TCP_DEFAULT_PORT
        if port == 0:
            raise ValueError(f"{url!r}: the port must be a number 1–65535")
        kind: TransportKind = "visca-ip" if scheme == "visca-ip" else "tcp"
        return CameraUrl(kind, parts.hostname, port)
    # A bare path, or another pyserial URL handler (loop://, socket://, rfc2217://).
    return CameraUrl("serial", text)


def _baud(query: str, url: str) -> int | None:
    values = parse_qs(query).get("baud")
    if not values:
        return None
    try:
        baud = int(values[-1])
    except ValueError:
        baud = 0
    if baud <= 0:
        raise ValueError(f"{url!r}: baud must be a positive integer, e.g. ?baud=9600")
    return baud
