"""The C allocator's settings for a long-running daemon (glibc only; elsewhere nothing).

Measured with ``python -m hil soak --probe 0`` (it samples glibc's ``mallinfo2`` and the
resident memory by kind of mapping inside the daemon): after the first two minutes the daemon's
heap stops growing and what is in use in it is flat, yet the resident memory moved — glibc
trimmed the top of a heap and grew it again in ~1 MiB steps (its *dynamic* thresholds: freeing
a frame-sized buffer that was mmap'd raises the mmap threshold to its size and the trim
threshold to twice that, so frames then come from the heap and the heap's top is given back
and taken again as they come and go), and a least-squares slope over 15 minutes read such steps
as 1-2 MiB/hour of growth that is not there. So the thresholds are fixed at start, at the
values the dynamic policy tends to anyway (:data:`MMAP_THRESHOLD`, twice that for the trim), and
the number of arenas is bounded (:data:`ARENA_MAX`; glibc's default is 8 per core, each with its
own free memory). Measured the other way too: a periodic ``malloc_trim(0)`` makes the resident
memory saw-tooth by ±1 MiB around the same level (not adopted).

It applies however the daemon is started (the systemd unit, ``dffd run``, ``make run``). A user
who sets glibc's own allocator variables (``MALLOC_ARENA_MAX``, ``MALLOC_TRIM_THRESHOLD_``, …,
or ``GLIBC_TUNABLES`` with ``glibc.malloc``) keeps them: then nothing here changes anything.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
from collections.abc import Mapping

__all__ = ["ARENA_MAX", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "configure"]

_LOGGER = logging.getLogger(__name__)

# Two arenas: the event loop and the estimator thread allocate concurrently all the time (frames,
# payloads); the other threads (log writer, VISCA reader, the simulator's renderer) little.
ARENA_MAX = 2
# glibc's upper bound for its dynamic mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX):
# frames up to 32 MiB (a 1920×1080 BGR frame is 6 MiB) come from the heap, as they do under the
# dynamic policy once one was freed, and bigger blocks are mmap'd and given back when freed.
MMAP_THRESHOLD = 32 * 1024 * 1024
# Free memory at a heap's top is given back beyond this (glibc's dynamic rule: twice the mmap
# threshold): the daemon's working set comes and goes well below it.
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD
# mallopt parameter numbers (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
# Environment variables by which a user (or glibc's tunables) already chose.
_USER_SETTINGS = (
    "MALLOC_ARENA_MAX",
    "MALLOC_ARENA_TEST",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_TOP_PAD_",
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_MMAP_MAX_",
)


def configure(environ: Mapping[str, str] | None = None) -> bool:
    """Apply the settings above unless the user chose allocator settings; True if applied.

    Call it before the daemon starts its threads (arenas are created as threads allocate).
    """
    env = os.environ if environ is None else environ
    if _user_chose(env):
        _LOGGER.info("allocator: settings from the environment kept")
        return False
    libc = _glibc()
    if libc is None:
        return False
    settings = (
        (_M_ARENA_MAX, ARENA_MAX, "M_ARENA_MAX"),
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD, "M_MMAP_THRESHOLD"),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD, "M_TRIM_THRESHOLD"),
    )
    for param, value, name in settings:
        if not libc.mallopt(param, value):
            _LOGGER.warning("allocator: mallopt(%s, %d) refused", name, value)
            return False
    return True


def _user_chose(env: Mapping[str, str]) -> bool:
    return any(k in env for k in _USER_SETTINGS) or "glibc.malloc" in env.get("GLIBC_TUNABLES", "")


def _glibc() -> ctypes.CDLL | None:
    """The process's C library if it is glibc (has ``mallopt``)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no such functions
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return libc
