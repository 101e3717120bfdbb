"""A command on a real pseudo-terminal, with one key typed when its output shows a cue.

The key goes through the terminal's line discipline, as a keyboard's does: Ctrl-C (0x03) becomes
a SIGINT to the terminal's foreground process group, Ctrl-D (0x04) the end of input at a line's
start. Used by the tests of ``dffd run`` stopped at a terminal and of ``dffd calibrate``'s prompts.
"""

from __future__ import annotations

import os
import pty
import re
import select
import signal
import time
from pathlib import Path

CTRL_C = b"\x03"
CTRL_D = b"\x04"
_READ_S = 0.05  # select() period while reading the terminal


def type_at_cue(
    argv: list[str],
    cwd: Path,
    env: dict[str, str],
    cue: re.Pattern[bytes],
    key: bytes,
    cue_timeout_s: float,
    exit_timeout_s: float,
) -> tuple[int, str]:
    """Run ``argv`` on a new pty, type ``key`` once its output matches ``cue``; (exit code,
    output). Fails when the cue does not come within ``cue_timeout_s`` or the process does not
    exit within ``exit_timeout_s`` of the key; the process is killed on the way out."""
    pid, fd = pty.fork()
    if pid == 0:  # the child: the pty is its controlling terminal, it leads a new session
        os.chdir(cwd)
        signal.signal(signal.SIGINT, signal.SIG_DFL)  # as at a terminal, whatever pytest inherited
        os.execvpe(argv[0], argv, env)
    out = bytearray()
    deadline = time.monotonic() + cue_timeout_s
    typed = False
    try:
        while True:
            if not typed and cue.search(out):
                os.write(fd, key)
                typed = True
                deadline = time.monotonic() + exit_timeout_s
            if time.monotonic() > deadline:
                what = f"no exit after {key!r}" if typed else f"no {cue.pattern!r} in the output"
                raise AssertionError(f"{what}:\n{out.decode(errors='replace')[-3000:]}")
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
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
    return os.waitstatus_to_exitcode(status), out.decode(errors="replace")
