"""``python -m dffd.warmup``: compile the tracker's kernels into the numba cache ahead of a start.

Run once after every install or upgrade, as the user the service runs as and with its
``NUMBA_CACHE_DIR`` (``make setup`` does it for the development tree): the first ``dffd run``
then loads machine code (~1-2 s) instead of compiling it (~15-40 s of CPU). Exit 0 when the
kernels are cached, 1 when no cache directory is writable (the message says which variable to
set). ``dffd run`` needs neither: :func:`start_background` lets the tracker use the kernels'
NumPy twins and, when the cache is not warm (:func:`dffd.cli.loading.kernels_warm`), runs this
command in a separate, niced process, then swaps the compiled kernels in; with a warm cache it
only loads them, in a thread of the service (~1 s of CPU, no second process).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["EXIT_FAILURE", "EXIT_OK", "BackgroundWarmup", "main", "start_background"]

EXIT_OK = 0
EXIT_FAILURE = 1
# The warm-up process compiles the kernels in 15-45 s of CPU on the 2-core reference machine
# (idle to loaded) and loads them in ~2 s; ten times the slow case is a hung compiler.
WARMUP_PROCESS_TIMEOUT_S = 450.0
# How long stop() waits for a terminated warm-up process to exit before killing it.
WARMUP_STOP_TIMEOUT_S = 5.0
# The warm-up process's niceness: on a busy machine the service's own threads come first.
WARMUP_NICENESS = 10

logger = logging.getLogger(__name__)


class BackgroundWarmup:
    """Compiles (or loads) the kernels in a separate process, then makes them run in this one."""

    def __init__(self, timeout_s: float = WARMUP_PROCESS_TIMEOUT_S, *, spawn: bool = True) -> None:
        self.done = threading.Event()  # set when the compiled kernels run (or the attempt ended)
        self.spawn = spawn  # False: the cache is warm, load the kernels here without a process
        self._timeout_s = timeout_s
        self._stopping = threading.Event()
        self._proc: subprocess.Popen[bytes] | None = None
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="dffd-kernels", daemon=True)

    def start(self) -> None:
        """Start the warm-up process and the thread that waits for it."""
        self._t0 = time.monotonic()
        self._thread.start()

    def stop(self) -> None:
        """Stop the warm-up process if it still runs (the service is shutting down)."""
        self._stopping.set()
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(WARMUP_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def _run(self) -> None:
        from dffd.core import kernel_dispatch

        try:
            ok = self._warm_up_process() if self.spawn else True
            if self._stopping.is_set():
                return
            if not ok:
                logger.warning(
                    "the kernels' warm-up process failed: compiling them in this process "
                    "(~15-40 s of CPU); run `python -m dffd.warmup` to see why"
                )
            kernel_dispatch.use_compiled()
            logger.info(
                "tracker kernels: compiled ones in use %.1f s after start (NumPy twins before; %s)",
                time.monotonic() - self._t0,
                "compiled by a warm-up process" if self.spawn else "loaded from numba's cache",
            )
        finally:
            self.done.set()

    def _warm_up_process(self) -> bool:
        """Run ``python -m dffd.warmup`` (niced); True when it cached the kernels."""
        env = dict(os.environ)
        # the same dffd as this process's, whether installed or run from a source tree
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self._proc = proc = subprocess.Popen(
            [sys.executable, "-m", "dffd.warmup"],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        if self._stopping.is_set():  # stop() came before the process existed: end it now
            proc.terminate()
        with contextlib.suppress(OSError):  # already gone, or not allowed: it yields less
            os.setpriority(os.PRIO_PROCESS, proc.pid, WARMUP_NICENESS)
        try:
            _, err = proc.communicate(timeout=self._timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            logger.warning("the kernels' warm-up process took over %.0f s", self._timeout_s)
            return False
        if proc.returncode != 0 and not self._stopping.is_set():
            logger.warning(
                "python -m dffd.warmup exited %d: %s",
                proc.returncode,
                err.decode(errors="replace").strip()[-500:],
            )
        return proc.returncode == 0


def start_background() -> BackgroundWarmup:
    """The kernels' NumPy twins from now on, the compiled ones once they are loaded (a warm
    cache) or a warm-up process has compiled them (a cold one)."""
    from dffd.cli.loading import kernels_warm
    from dffd.core import kernel_dispatch

    kernel_dispatch.use_numpy()
    warm = BackgroundWarmup(spawn=not kernels_warm())
    warm.start()
    return warm


def main(argv: Sequence[str] | None = None) -> int:
    """Compile or load every kernel, print where the cache is and how long it took."""
    parser = argparse.ArgumentParser(
        prog="python -m dffd.warmup", description=(__doc__ or "").split("\n\n", 1)[1]
    )
    parser.parse_args(argv)
    from dffd.cli.loading import kernels_warm

    if not kernels_warm():
        # a first compilation takes a minute or more with nothing else to show for it
        print(
            "dffd warmup: compiling the tracker's kernels into the numba cache, once after an "
            "install (15-40 s of CPU; a minute or two on a busy 2-core machine)...",
            flush=True,
        )
    t0 = time.perf_counter()
    from dffd.core import kernels  # the import is what compiles (or loads) the kernels

    seconds = time.perf_counter() - t0
    report = kernels.cache_report()
    if report.uncached:
        print(
            f"dffd warmup: no writable numba cache (NUMBA_CACHE_DIR="
            f"{os.environ.get('NUMBA_CACHE_DIR', 'unset')}): every start compiles the kernels in "
            "memory. Set NUMBA_CACHE_DIR to a directory the service user can write (the systemd "
            "unit uses /var/lib/dffd/.numba) and run this again.",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    how = (
        f"compiled {report.compiled} and loaded {report.loaded}"
        if report.compiled
        else f"loaded {report.loaded} from the cache"
    )
    print(
        f"{report.kernels} kernels ready in {seconds:.1f} s ({how}); "
        f"cache: {', '.join(report.cache_dirs)}"
    )
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
