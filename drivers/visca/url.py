"""The camera port as one URL: which transport carries the VISCA bytes, and where to.

``[camera] port`` accepts

* ``serial:///dev/visca0?baud=9600`` or a bare absolute path (``/dev/ttyUSB0``): RS-232; one of
  pyserial's own URL handlers (``socket://host:port``, ``rfc2217://host:port``, ``loop://``, …)
  also goes to pyserial;
* ``visca-ip://192.168.0.100:52381`` (port 52381 if omitted): VISCA over IP, UDP;
* ``tcp://192.168.0.100:5678`` (port 5678 if omitted): raw VISCA over TCP (PTZOptics style).

Anything else is refused here, before a transport is opened: an unknown scheme, a host without
one (``visca-ip//host``, ``192.168.0.100``) or a relative path would otherwise reach pyserial and
fail only when the link opens, as a missing serial device.

:func:`parse_camera_url` is pure; a ValueError says what was wrong and lists :data:`FORMS`.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass
from typing import Literal
from urllib.parse import parse_qs, urlsplit

VISCA_IP_DEFAULT_PORT = 52381  # Sony's VISCA-over-IP port
RAW_TCP_DEFAULT_PORT = 5678  # PTZOptics' raw VISCA TCP port

TransportKind = Literal["serial", "visca-ip", "tcp"]
# Every form a camera port takes; each error ends with it.
FORMS = (
    "a serial device (/dev/ttyUSB0, serial:///dev/visca0?baud=9600), visca-ip://HOST[:52381], "
    "tcp://HOST[:5678] or a pyserial URL (socket://HOST:PORT, rfc2217://HOST:PORT, loop://)"
)
# pyserial's own URL handlers (the modules serial.urlhandler.protocol_* of pyserial 3.5): the
# serial transport opens these with serial.serial_for_url, which checks the rest.
PYSERIAL_SCHEMES = frozenset({"alt", "cp2110", "hwgrep", "loop", "rfc2217", "socket", "spy"})
_OWN_SCHEMES = ("serial", "visca-ip", "tcp")
_SCHEMES = (*_OWN_SCHEMES, *sorted(PYSERIAL_SCHEMES))
# Schemes that are not camera ports but say which one was meant: VISCA over IP runs on UDP
# (`dffd sim-camera --listen udp://…` serves it, and prints its visca-ip:// URL).
_MEANT = {"udp": "visca-ip"}
# A known scheme written without "://" ("visca-ip//host", "tcp:host", "serial:/dev/x").
_SCHEME_TYPO_RE = re.compile(
    rf"(?P<scheme>{'|'.join(re.escape(s) for s in (*_SCHEMES, *_MEANT))})[:/]+(?P<rest>.*)",
    re.IGNORECASE,
)
# A host name or IPv4 address, maybe with a port: a network camera given without a scheme.
_HOST_RE = re.compile(r"[A-Za-z0-9-]+(\.[A-Za-z0-9-]+)+(:\d{1,5})?")


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
        raise _invalid(url, "it is empty")
    scheme, sep, rest = text.partition("://")
    if not sep:
        return _bare(url, text)
    scheme = scheme.lower()
    if scheme == "serial":
        parts = urlsplit(text)
        if parts.netloc:
            # serial://dev/ttyUSB0 would open /ttyUSB0: "dev" parses as a host
            raise _invalid(
                url, "serial:// takes an absolute path", f"serial:///{parts.netloc}{parts.path}"
            )
        if not parts.path:
            raise _invalid(url, "it names no device")
        return CameraUrl("serial", parts.path, baudrate=_baud(parts.query, url))
    if scheme in ("visca-ip", "tcp"):
        parts = urlsplit(text)
        if not parts.hostname:
            raise _invalid(url, f"it names no host (e.g. {scheme}://192.168.0.100)")
        try:
            port = parts.port
        except ValueError as exc:
            raise _invalid(url, "the port must be a number 1–65535") from exc
        if port is None:
            port = VISCA_IP_DEFAULT_PORT if scheme == "visca-ip" else RAW_TCP_DEFAULT_PORT
        if port == 0:
            raise _invalid(url, "the port must be a number 1–65535")
        kind: TransportKind = "visca-ip" if scheme == "visca-ip" else "tcp"
        return CameraUrl(kind, parts.hostname, port)
    if scheme in PYSERIAL_SCHEMES:
        return CameraUrl("serial", text)
    close = difflib.get_close_matches(scheme, _SCHEMES, n=1)
    meant = _MEANT.get(scheme) or (close[0] if close else None)
    guesses = [f"{meant}://{rest}"] if meant else []
    raise _invalid(url, f"unknown scheme {scheme!r}", *guesses)


def _bare(url: str, text: str) -> CameraUrl:
    """A value without ``://``: a serial device's absolute path, else an error with a guess."""
    if text.startswith("/"):
        return CameraUrl("serial", text)
    typo = _SCHEME_TYPO_RE.fullmatch(text)
    if typo is not None:
        scheme = typo["scheme"].lower()
        scheme = _MEANT.get(scheme, scheme)
        rest = typo["rest"]
        guess = f"serial:///{rest.lstrip('/')}" if scheme == "serial" else f"{scheme}://{rest}"
        raise _invalid(url, "it has no '://' after the scheme", guess)
    if _HOST_RE.fullmatch(text):
        raise _invalid(
            url, "a network camera needs a scheme", f"visca-ip://{text}", f"tcp://{text}"
        )
    raise _invalid(url, "a serial device is an absolute path, e.g. /dev/ttyUSB0")


def _invalid(url: str, problem: str, *guesses: str) -> ValueError:
    """``'<url>' is not a camera port: <problem>[ (did you mean '<guess>'?)]; use <FORMS>``."""
    hint = f" (did you mean {' or '.join(repr(g) for g in guesses)}?)" if guesses else ""
    return ValueError(f"{url!r} is not a camera port: {problem}{hint}; use {FORMS}")


def _baud(query: str, url: str) -> int | None:
    values = parse_qs(query).get("baud")
    if not values:
        return None
    try:
        baud = int(values[-1])
    except ValueError:
        baud = 0
    if baud <= 0:
        raise _invalid(url, "baud must be a positive integer (?baud=9600)")
    return baud
