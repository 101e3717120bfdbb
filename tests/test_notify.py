"""sd_notify: messages reach the socket, no-op without systemd, watchdog period from the env."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from dffd.daemon.notify import Notifier

RECV_TIMEOUT_S = 2.0  # a local datagram arrives at once; this only bounds a failing test


def test_messages_reach_the_notify_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        server.settimeout(RECV_TIMEOUT_S)
        notifier = Notifier(environ={"NOTIFY_SOCKET": path})
        assert notifier.enabled
        assert notifier.ready("tracking at 30 fps")
        assert server.recv(4096) == b"READY=1\nSTATUS=tracking at 30 fps"
        assert notifier.watchdog()
        assert server.recv(4096) == b"WATCHDOG=1"
        assert notifier.status("two\nlines")
        assert server.recv(4096) == b"STATUS=two lines"
        assert notifier.stopping()
        assert server.recv(4096) == b"STOPPING=1"


def test_no_op_without_systemd() -> None:
    notifier = Notifier(environ={})
    assert not notifier.enabled
    assert notifier.ready() is False
    assert notifier.watchdog_period_s is None


def test_missing_socket_is_not_fatal(tmp_path: Path) -> None:
    notifier = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    assert notifier.watchdog() is False
    assert notifier.watchdog() is False


def test_watchdog_period_is_half_of_watchdog_sec() -> None:
    mine = str(os.getpid())
    assert Notifier(environ={"WATCHDOG_USEC": "10000000"}).watchdog_period_s == 5.0
    assert Notifier(environ={"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": mine}).watchdog_period_s
    assert (
        Notifier(environ={"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}).watchdog_period_s
        is None
    )
    assert Notifier(environ={"WATCHDOG_USEC": "junk"}).watchdog_period_s is None
