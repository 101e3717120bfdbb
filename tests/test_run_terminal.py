"""``dffd run`` as a user at a terminal runs it: in a real pseudo-terminal, stopped by Ctrl-C.

Ctrl-C is the byte 0x03 typed into the terminal, so the line discipline sends SIGINT to the
terminal's foreground process group exactly as a keyboard does. The daemon runs under ``make``
(the README's ``make run``): make and dffd start in one process group, and make dies of a SIGINT
it receives itself, whatever dffd does, so this checks that dffd keeps Ctrl-C to itself, stops in
order and that make then exits 0. The embedded broker and the dashboard move to free ports.
"""

from __future__ import annotations

import os
import pty
import re
import select
import shutil
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import free_port

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make"),
]

# Interpreter start, imports, kernels from the cache, broker, camera init, first frames on a
# loaded 2-core machine: the README run path's own test allows 20 s for the broker alone.
READY_TIMEOUT_S = 40.0
# The daemon's shutdown is bounded by 10 s (dffd.daemon.app.SHUTDOWN_TIMEOUT_S).
EXIT_TIMEOUT_S = 15.0
READY = re.compile(rb"ready: camera initialised and frames flowing")
CTRL_C = b"\x03"
_READ_S = 0.05  # select() period while reading the terminal


def _run_in_terminal(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[int, str]:
    """Run ``argv`` on a new pty, type Ctrl-C once the daemon is ready; (exit code, output)."""
    pid, fd = pty.fork()
    if pid == 0:  # the child: the pty is its controlling terminal, it leads a new session
        os.chdir(cwd)
        os.execvpe(argv[0], argv, env)
    out = bytearray()
    deadline = time.monotonic() + READY_TIMEOUT_S
    typed = False
    try:
        while True:
            if not typed and READY.search(out):
                os.write(fd, CTRL_C)
                typed = True
                deadline = time.monotonic() + EXIT_TIMEOUT_S
            if time.monotonic() > deadline:
                raise AssertionError(
                    ("no exit after Ctrl-C" if typed else "daemon not ready")
                    + ":\n"
                    + out.decode(errors="replace")[-3000:]
                )
            ready, _, _ = select.select([fd], [], [], _READ_S)
            if ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:  # EIO: every process holding the terminal has exited
                    break
                if not data:
                    break
                out += data
        _, status = os.waitpid(pid, 0)
    finally:
        os.close(fd)
        try:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
    return os.waitstatus_to_exitcode(status), out.decode(errors="replace")


@pytest.mark.timeout(90)
def test_ctrl_c_under_make_run_stops_dffd_cleanly_and_make_exits_0(tmp_path: Path) -> None:
    makefile = tmp_path / "Makefile"
    makefile.write_text(f"run:\n\t{sys.executable} -m dffd run\n", encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(
        DFFD_MQTT__EMBEDDED_PORT=str(free_port()),
        DFFD_WEB__LISTEN=f"127.0.0.1:{free_port()}",
        DFFD_LOG__DIR=str(tmp_path / "log"),
        COLUMNS="120",
        LINES="50",
    )
    code, text = _run_in_terminal(["make", "-s", "-f", str(makefile), "run"], tmp_path, env)
    assert code == 0, text[-3000:]
    assert "dffd stopped cleanly on Ctrl-C (SIGINT)" in text, text[-3000:]
    assert "pan/tilt stopped" in text
    assert "Interrupt" not in text  # make's own "*** [run] Interrupt"
