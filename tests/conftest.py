"""Shared pytest fixtures."""

from __future__ import annotations

import getpass
import shutil
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

# -- a real mosquitto broker on a free loopback port -----------------------------------------

MOSQUITTO_CANDIDATES = ("/usr/sbin/mosquitto", "/usr/bin/mosquitto")
# mosquitto binds its listener within a few ms of exec; 5 s covers a loaded 2-core CI machine.
MOSQUITTO_START_TIMEOUT_S = 5.0
# SIGTERM to exit: mosquitto closes its sockets at once.
MOSQUITTO_STOP_TIMEOUT_S = 5.0
_PORT_POLL_S = 0.01  # connect() retry period while waiting for the listener


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def wait_for_port(host: str, port: int, timeout_s: float) -> None:
    """Block until ``host:port`` accepts a TCP connection (TimeoutError after ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=_PORT_POLL_S * 10):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise TimeoutError(f"nothing accepts connections on {host}:{port}") from None
            time.sleep(_PORT_POLL_S)


class Mosquitto:
    """A mosquitto process on ``host:port`` that a test can stop and start again (same port)."""

    def __init__(
        self,
        binary: str,
        workdir: Path,
        port: int,
        host: str = "127.0.0.1",
        listener_options: str = "allow_anonymous true\n",
    ) -> None:
        self.binary = binary
        self.host = host
        self.port = port
        self.config_file = workdir / "mosquitto.conf"
        self.log_file = workdir / "mosquitto.log"
        self.config_file.write_text(
            f"listener {port} {host}\n"
            f"{listener_options}"
            "persistence false\n"
            # mosquitto started as root drops to user 'mosquitto', which cannot read files in
            # the test's private tmp directory; stay the invoking user instead.
            f"user {getpass.getuser()}\n"
            "set_tcp_nodelay true\n"
            "log_dest stderr\n"
            "log_type error\n"
            "log_type warning\n"
            "log_type notice\n",
            encoding="utf-8",
        )
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """``mqtt://host:port``."""
        return f"mqtt://{self.host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self) -> None:
        """Start the broker and wait until its port accepts connections."""
        if self.running:
            return
        log = self.log_file.open("ab")
        self._process = subprocess.Popen(
            [self.binary, "-c", str(self.config_file)], stdout=log, stderr=log
        )
        log.close()
        try:
            wait_for_port(self.host, self.port, MOSQUITTO_START_TIMEOUT_S)
        except TimeoutError:
            self.stop()
            log_text = self.log_file.read_text(errors="replace")
            raise RuntimeError(f"mosquitto did not start on {self.port}:\n{log_text}") from None

    def stop(self) -> None:
        """Stop the broker (SIGTERM, then SIGKILL) and wait for it to exit."""
        process, self._process = self._process, None
        if process is None:
            return
        process.terminate()
        try:
            process.wait(MOSQUITTO_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(MOSQUITTO_STOP_TIMEOUT_S)


def _mosquitto_binary() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    return next((c for c in MOSQUITTO_CANDIDATES if Path(c).is_file()), None)


MosquittoFactory = Callable[..., Mosquitto]


@pytest.fixture
def mosquitto_factory(tmp_path: Path) -> Iterator[MosquittoFactory]:
    """``factory(listener_options="...")`` starts a mosquitto on a free port; all stopped after."""
    binary = _mosquitto_binary()
    if binary is None:
        pytest.skip("mosquitto is not installed (Debian package 'mosquitto'; `make system-deps`)")
    brokers: list[Mosquitto] = []

    def factory(**options: str) -> Mosquitto:
        workdir = tmp_path / f"mosquitto{len(brokers)}"
        workdir.mkdir()
        broker = Mosquitto(binary, workdir, free_port(), **options)
        brokers.append(broker)
        broker.start()
        return broker

    try:
        yield factory
    finally:
        for broker in brokers:
            broker.stop()


@pytest.fixture
def mosquitto(mosquitto_factory: MosquittoFactory) -> Mosquitto:
    """A running mosquitto on a free 127.0.0.1 port (anonymous, no persistence)."""
    return mosquitto_factory()
