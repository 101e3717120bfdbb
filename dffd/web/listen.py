"""``[web] listen`` addresses: parsing and the loopback rule (no aiohttp: the config imports it)."""

from __future__ import annotations

import ipaddress


class WebError(Exception):
    """Root of the dashboard's errors."""


class WebConfigError(WebError):
    """``[web]`` settings that cannot be served safely or at all."""


def parse_listen(listen: str) -> tuple[str, int]:
    """``"HOST:PORT"`` or ``"[IPv6]:PORT"`` → (host, port); raises WebConfigError."""
    host, sep, port_text = listen.strip().rpartition(":")
    if not sep or not host:
        raise WebConfigError(f'web.listen = {listen!r}: give "HOST:PORT", e.g. "127.0.0.1:8080"')
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        port = int(port_text)
    except ValueError:
        raise WebConfigError(f"web.listen = {listen!r}: the port must be a number") from None
    if not 0 <= port <= 65535:
        raise WebConfigError(f"web.listen = {listen!r}: the port must be within 0..65535")
    return host, port


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (127.0.0.0/8, ::1)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything
