"""The operator at the terminal in ``dffd calibrate``'s lab procedure.

The lab procedure asks the operator to place the target at each depth and press Enter
(:func:`ask_operator`); those prompts need an interactive terminal on stdin. Under systemd, from
a pipe or with ``</dev/null`` there is none, and Enter queued in a pipe would confirm placements
nobody made: :func:`terminal_problem` says so before anything starts. At a prompt Ctrl-D ends
the procedure (:class:`InputEndedError`) and Ctrl-C stops the wait at once; :func:`stopped_message`
says what had been measured and that no table was written.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import stat
import sys
import termios
from collections.abc import Sequence
from pathlib import Path

__all__ = ["STDIN_FD", "InputEndedError", "ask_operator", "stopped_message", "terminal_problem"]

STDIN_FD = 0
_READ_BYTES = 1024  # one read of a terminal line (canonical mode returns at most a line)


class InputEndedError(EOFError):
    """The terminal's input ended at a prompt (Ctrl-D, or the terminal went away)."""


def terminal_problem(n_depths: int, fd: int = STDIN_FD) -> str | None:
    """Why the lab procedure's prompts cannot be answered on ``fd`` (stdin), or None: it is an
    interactive terminal. Checked before the procedure (the camera, the kernels, the sweeps)."""
    what = _not_a_terminal(fd)
    if what is None:
        return None
    return (
        f"the lab procedure asks the operator to place the target at each of its {n_depths} "
        f"depths and press Enter, but stdin is {what}, not a terminal: nobody can answer, and "
        "answers queued in a pipe or a file would confirm placements nobody made; run it from "
        "an interactive terminal (over ssh: ssh -t HOST dffd calibrate …)"
    )


async def ask_operator(text: str, fd: int = STDIN_FD) -> None:
    """Show ``text`` and wait for Enter on the terminal ``fd``; :class:`InputEndedError` at Ctrl-D.
    Cancelling the wait (Ctrl-C) returns at once."""
    # Not input() in a worker thread: cancelling the wait cannot stop the thread, and after
    # Ctrl-C the process would wait for an Enter to exit. Keys typed during the last sweep (an
    # early Enter) are dropped: only an Enter after this prompt confirms this placement.
    with contextlib.suppress(termios.error, OSError):
        termios.tcflush(fd, termios.TCIFLUSH)
    sys.stdout.write(text)
    sys.stdout.flush()
    loop = asyncio.get_running_loop()
    line = b""
    while not line.endswith(b"\n"):
        readable: asyncio.Future[None] = loop.create_future()
        loop.add_reader(fd, _set_done, readable)
        try:
            await readable
        finally:
            loop.remove_reader(fd)
        try:
            chunk = os.read(fd, _READ_BYTES)
        except OSError:  # EIO: the terminal hung up
            chunk = b""
        if not chunk:  # Ctrl-D at the start of a line (or twice after some keys), or a hang-up
            raise InputEndedError("the input ended at the prompt")
        line += chunk


def stopped_message(why: str, depths: Sequence[float], swept: int, out: Path | None) -> str:
    """What a procedure the operator stopped (``why``) had done: where it stopped, how many of
    ``depths`` had been measured (``swept`` sweeps: the depths in order, then repeats), that
    they are not kept and that no lens table was written."""
    n = len(depths)
    done = min(swept, n)
    if done < n:
        where = f"at {depths[done]:g} m (depth {done + 1} of {n})"
        measured = f"{done} of the {n} depths measured"
        if done:
            measured += f" ({_span(depths[:done])})"
    else:
        where = "after the last depth"
        measured = f"all {n} depths measured"
        if swept > n:
            measured += f" and {swept - n} swept again"
    if swept:
        measured += ", not kept (a table is fitted from the sweeps of one whole run)"
    written = (
        f"no lens file was written: --out {out} is as it was"
        if out is not None
        else "no lens table was printed"
    )
    return f"stopped {where}, {why}: {measured}; {written}"


# -- private helpers --------------------------------------------------------------------------
def _not_a_terminal(fd: int) -> str | None:
    """What ``fd`` is when it is not a terminal ("a pipe", "closed", …), or None."""
    try:
        if os.isatty(fd):
            return None
        found = os.fstat(fd)
    except OSError:
        return "closed"
    with contextlib.suppress(OSError):
        if os.path.samestat(found, Path(os.devnull).stat()):
            return f"{os.devnull} (as under systemd or with </dev/null)"
    if stat.S_ISFIFO(found.st_mode):
        return "a pipe"
    if stat.S_ISSOCK(found.st_mode):
        return "a socket"
    if stat.S_ISREG(found.st_mode):
        return "a file"
    return "a device"


def _span(depths: Sequence[float]) -> str:
    """``2 m`` or ``1 to 4.5 m`` (the first and last of ``depths``)."""
    if len(depths) == 1:
        return f"{depths[0]:g} m"
    return f"{depths[0]:g} to {depths[-1]:g} m"


def _set_done(future: asyncio.Future[None]) -> None:
    # the reader fires on every loop turn while the fd stays readable, until it is removed
    if not future.done():
        future.set_result(None)
