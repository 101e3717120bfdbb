"""``python -m hil.threadnames dffd ARGS…``: run the dffd CLI with kernel-visible thread names.

Python (before 3.14) does not give its threads a name the kernel sees: every thread of the daemon
is ``python`` in ``/proc/PID/task/*/comm``. This shim sets each thread's kernel name to its
Python name (``prctl(PR_SET_NAME)``, first 15 bytes) when it starts — ``dffd-estimator``,
``dffd-jsonlog``, ``sim-render`` (the simulated frame source) — and the main
thread's to ``dffd-loop``, then runs ``python -m dffd ARGS…`` unchanged. The soak reads the CPU
of each thread by that name. Bench-only: the product does not depend on it.
"""

from __future__ import annotations

import ctypes
import os
import runpy
import sys
import threading
from typing import Any

PR_SET_NAME = 15
MAIN_THREAD_NAME = "dffd-loop"
SWITCH_INTERVAL_ENV = "HIL_SWITCH_INTERVAL_S"


def set_native_name(name: str) -> None:
    """Set the calling thread's kernel name (``comm``); silently nothing where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):  # not Linux/glibc: the names are a nicety
        return


def install() -> None:
    """Name every thread started from now on after its Python name."""
    original: Any = threading.Thread._bootstrap_inner  # type: ignore[attr-defined]

    def bootstrap_inner(self: threading.Thread) -> None:
        set_native_name(self.name)
        original(self)

    threading.Thread._bootstrap_inner = bootstrap_inner  # type: ignore[attr-defined]


def main() -> None:
    """Install the names and run the module named by the first argument as ``__main__``."""
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m hil.threadnames MODULE [ARGS…]")
    install()
    set_native_name(MAIN_THREAD_NAME)
    switch = os.environ.get(SWITCH_INTERVAL_ENV)
    if switch:  # A/B runs of the GIL hand-over interval (Python's default: 5 ms)
        sys.setswitchinterval(float(switch))
    module = sys.argv[1]
    sys.argv = [module, *sys.argv[2:]]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
