"""The terminal's foreground process group for ``dffd run`` (so Ctrl-C reaches dffd alone).

Ctrl-C makes the terminal send SIGINT to its whole foreground process group. Started by
``make run``, dffd shares that group with ``make``, which on SIGINT waits for its child and then
kills itself with SIGINT, so the shell sees 130 however cleanly dffd stopped. While the daemon
runs it therefore takes the terminal's foreground for a process group of its own, so Ctrl-C is
the daemon's orderly shutdown alone and ``make`` returns dffd's exit code; on leaving it hands
the foreground back. Ctrl-Z is ignored meanwhile: a stopped daemon in its own group would leave
the terminal to a process nobody can resume (``make``'s shell does not know it). Nothing is
done when stdin is not a terminal, when dffd is not in the foreground, or when it already leads
its process group (started directly by an interactive shell); ``dffd run`` asks for it only with
its live console view (a daemon that a script or a test starts leaves Ctrl-C to its parent).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
from collections.abc import Iterator

_LOGGER = logging.getLogger(__name__)

__all__ = ["own_foreground"]


@contextlib.contextmanager
def own_foreground(fd: int = 0) -> Iterator[bool]:
    """Inside: this process leads the terminal's foreground process group (yields whether it
    changed anything); afterwards the previous group has the foreground again."""
    previous = _foreground_to_take(fd)
    if previous is None:
        yield False
        return
    old_tstp = signal.signal(signal.SIGTSTP, signal.SIG_IGN)
    try:
        os.setpgid(0, 0)
        _set_foreground(fd, os.getpgrp())
    except OSError as exc:
        _LOGGER.debug("could not take the terminal's foreground: %s", exc)
        signal.signal(signal.SIGTSTP, old_tstp)
        yield False
        return
    try:
        yield True
    finally:
        with contextlib.suppress(OSError):
            _set_foreground(fd, previous)
        signal.signal(signal.SIGTSTP, old_tstp)


def _foreground_to_take(fd: int) -> int | None:
    """The foreground group to hand back later, or None when there is nothing to do."""
    try:
        if not os.isatty(fd):
            return None
        foreground = os.tcgetpgrp(fd)
    except OSError:
        return None
    group = os.getpgrp()
    if foreground != group or group == os.getpid():
        return None
    return foreground


def _set_foreground(fd: int, group: int) -> None:
    # tcsetpgrp from a background group raises SIGTTOU (stopping us) unless it is ignored.
    old_ttou = signal.signal(signal.SIGTTOU, signal.SIG_IGN)
    try:
        os.tcsetpgrp(fd, group)
    finally:
        signal.signal(signal.SIGTTOU, old_ttou)
