"""systemd service notification (sd_notify): READY, WATCHDOG, STATUS, STOPPING.

A datagram to ``$NOTIFY_SOCKET`` (sd_notify(3)); every call is a no-op when the process is not
run by systemd with ``Type=notify``. ``Notifier.watchdog_period_s`` is half of ``WatchdogSec``
(the interval sd_watchdog_enabled(3) recommends); the daemon pings only while frames flow, so a
stalled camera makes systemd restart the service.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

__all__ = ["Notifier"]

_LOGGER = logging.getLogger(__name__)

_USEC_PER_S = 1_000_000


class Notifier:
    """Sends sd_notify messages to ``socket_path`` (default: ``$NOTIFY_SOCKET``)."""

    def __init__(
        self, socket_path: str | None = None, environ: Mapping[str, str] | None = None
    ) -> None:
        env = os.environ if environ is None else environ
        self.socket_path = socket_path if socket_path is not None else env.get("NOTIFY_SOCKET")
        self.watchdog_period_s = _watchdog_period(env)
        self._failed = False

    @property
    def enabled(self) -> bool:
        """True when running under systemd (a notify socket is known)."""
        return bool(self.socket_path)

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up finished (camera initialised, frames flowing)."""
        return self.notify(READY="1", STATUS=status)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the service is alive (send every ``watchdog_period_s``)."""
        return self.notify(WATCHDOG="1")

    def status(self, text: str) -> bool:
        """``STATUS=…``: one line shown by ``systemctl status``."""
        return self.notify(STATUS=text)

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self.notify(STOPPING="1", STATUS=status)

    def notify(self, **fields: str | None) -> bool:
        """Send ``KEY=value`` lines (None values skipped); True if a datagram was sent."""
        if not self.socket_path:
            return False
        lines = [f"{key}={value}" for key, value in fields.items() if value is not None]
        message = "\n".join(line.replace("\n", " ") for line in lines).encode()
        address = self.socket_path
        if address.startswith("@"):  # abstract namespace socket
            address = "\0" + address[1:]
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.connect(address)
                sock.sendall(message)
        except OSError as exc:
            # Never fatal: a lost notification shows up as a watchdog restart, which is logged.
            (_LOGGER.debug if self._failed else _LOGGER.warning)(
                "sd_notify to %s failed: %s", self.socket_path, exc
            )
            self._failed = True
            return False
        return True


def _watchdog_period(env: Mapping[str, str]) -> float | None:
    """Half of WATCHDOG_USEC when the watchdog is meant for this process, else None."""
    usec = env.get("WATCHDOG_USEC")
    pid = env.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / _USEC_PER_S / 2 if value > 0 else None
