"""``python -m hil.memprobe dffd ARGS…``: run the dffd CLI with a memory probe inside it.

Bench-only (``python -m hil soak --probe``): the product does not depend on it. Like
:mod:`hil.threadnames` (whose thread names it installs too), it runs ``python -m dffd ARGS…``
unchanged, and adds a daemon thread that every ``HIL_MEMPROBE_PERIOD_S`` seconds appends one
JSON line to ``HIL_MEMPROBE_OUT`` with what the process's resident memory is made of:

* ``rss_anon_kib`` / ``rss_file_kib`` from ``/proc/self/status``;
* the resident anonymous memory by kind of mapping (``/proc/self/smaps``): the main heap
  (``[heap]``), 1 MiB mappings (CPython's object allocator takes its arenas from the kernel in
  1 MiB mappings and gives an arena back when it is empty; glibc's own mmap'd chunks of that
  size would count too, see ``hblkhd``), 8 MiB mappings (thread stacks), and the rest (glibc's
  64 MiB thread-arena heaps, other mmap'd buffers). Approximate: the kernel merges adjacent
  anonymous mappings of the same protection into one, which then counts as "other";
* glibc's ``mallinfo2()``: ``arena`` (bytes obtained with brk/mmap'd arena heaps),
  ``hblkhd`` (bytes in chunks mmap'd one by one), ``uordblks`` (in use), ``fordblks`` (free
  inside the heaps), ``keepcost`` (the releasable top);
* with ``HIL_MEMPROBE_TRACEMALLOC`` = N > 0 (traceback depth; tracemalloc started before the
  daemon imports anything): the traced bytes of Python objects and of NumPy's buffers (NumPy
  reports its data allocations to tracemalloc in its own domain), the number of live asyncio
  tasks and of gc-tracked objects, and the allocation sites whose traced size grew most since
  the first snapshot taken after ``HIL_MEMPROBE_BASELINE_S``.

mallinfo2 walks every arena under its lock and a tracemalloc snapshot of a few hundred thousand
blocks takes ~0.1 s with the GIL held: the probe perturbs latency, so probed runs measure memory
only.
"""

from __future__ import annotations

import ctypes
import gc
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

from hil import threadnames

OUT_ENV = "HIL_MEMPROBE_OUT"
PERIOD_ENV = "HIL_MEMPROBE_PERIOD_S"
TRACEMALLOC_ENV = "HIL_MEMPROBE_TRACEMALLOC"
BASELINE_ENV = "HIL_MEMPROBE_BASELINE_S"
# Default sampling period: RSS moves by allocator steps of ~1 MiB every few minutes; 10 s
# resolves them without the probe's own cost (a snapshot holds the GIL ~0.1 s) mattering.
DEFAULT_PERIOD_S = 10.0
# The histories and caches fill over the first ~2 minutes (see hil.soak.SLOPE_FRACTION): growth
# is counted from a snapshot after that.
DEFAULT_BASELINE_S = 120.0
# Allocation sites listed per sample (the largest growth first).
TOP_SITES = 15
# NumPy's tracemalloc domain (numpy/core/include/numpy/ndarraytypes.h: NPY_TRACE_DOMAIN).
NUMPY_DOMAIN = 389047
PROBE_THREAD_NAME = "hil-memprobe"


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def mallinfo2() -> dict[str, int]:
    """glibc's ``mallinfo2()`` of this process (empty where the C library has none)."""
    try:
        fn = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):
        return {}
    fn.restype = _MallInfo2
    info = fn()
    return {field[0]: int(getattr(info, field[0])) for field in _MallInfo2._fields_}


def rss_split_kib() -> dict[str, int]:
    """RssAnon, RssFile and VmRSS of this process, KiB."""
    out = {"rss_anon_kib": 0, "rss_file_kib": 0, "rss_kib": 0}
    keys = {"RssAnon:": "rss_anon_kib", "RssFile:": "rss_file_kib", "VmRSS:": "rss_kib"}
    for line in Path("/proc/self/status").read_text().splitlines():
        parts = line.split()
        if parts and parts[0] in keys:
            out[keys[parts[0]]] = int(parts[1])
    return out


def anon_by_mapping_kib() -> dict[str, int]:
    """Resident anonymous KiB by kind of mapping (see the module docstring), and their counts."""
    out = {"heap": 0, "one_mib": 0, "one_mib_count": 0, "stack_8mib": 0, "other": 0}
    size = 0
    name = ""
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split(maxsplit=5)
        if head and "-" in head[0] and not head[0].endswith(":"):
            lo, hi = (int(x, 16) for x in head[0].split("-"))
            size = (hi - lo) // 1024
            name = head[5] if len(head) > 5 else ""
        elif head and head[0] == "Anonymous:":
            kib = int(head[1])
            if name == "[heap]":
                out["heap"] += kib
            elif name:
                continue  # file mappings' private copies, [stack], vdso
            elif size == 1024:
                out["one_mib"] += kib
                out["one_mib_count"] += 1
            elif size == 8192:
                out["stack_8mib"] += kib
            else:
                out["other"] += kib
    return out


def main() -> None:
    """Start the probe thread, then run the module named by the first argument as __main__."""
    out = os.environ.get(OUT_ENV)
    depth = int(os.environ.get(TRACEMALLOC_ENV, "0") or 0)
    if depth > 0:
        import tracemalloc

        tracemalloc.start(depth)
    if out:
        period = float(os.environ.get(PERIOD_ENV, DEFAULT_PERIOD_S))
        baseline = float(os.environ.get(BASELINE_ENV, DEFAULT_BASELINE_S))
        probe = threading.Thread(
            target=_run, args=(Path(out), period, baseline, depth > 0), name=PROBE_THREAD_NAME
        )
        probe.daemon = True
        probe.start()
    threadnames.main()


def _run(out: Path, period_s: float, baseline_s: float, traced: bool) -> None:
    import asyncio

    started = time.monotonic()
    base: Any = None
    with out.open("a", encoding="utf-8") as fh:
        while True:
            time.sleep(period_s)
            t = time.monotonic() - started
            row: dict[str, Any] = {"t_s": t, **rss_split_kib(), "mallinfo2": mallinfo2()}
            row["anon_by_mapping_kib"] = anon_by_mapping_kib()
            row["threads"] = threading.active_count()
            if traced:
                import tracemalloc

                snap = tracemalloc.take_snapshot().filter_traces(
                    [tracemalloc.Filter(inclusive=False, filename_pattern=tracemalloc.__file__)]
                )
                numpy_b = sum(
                    s.size
                    for s in snap.filter_traces(
                        [tracemalloc.DomainFilter(inclusive=True, domain=NUMPY_DOMAIN)]
                    ).statistics("filename")
                )
                row["traced_bytes"] = tracemalloc.get_traced_memory()[0]
                row["numpy_bytes"] = numpy_b
                objs = gc.get_objects()
                row["gc_objects"] = len(objs)
                row["asyncio_tasks"] = sum(1 for o in objs if isinstance(o, asyncio.Task))
                del objs
                if base is None and t >= baseline_s:
                    base = snap
                    row["baseline"] = True
                elif base is not None:
                    row["top_growth"] = [
                        {
                            "site": str(d.traceback),
                            "size_diff_b": d.size_diff,
                            "size_b": d.size,
                            "count_diff": d.count_diff,
                        }
                        for d in sorted(
                            snap.compare_to(base, "lineno"), key=lambda d: -d.size_diff
                        )[:TOP_SITES]
                    ]
                del snap
            fh.write(json.dumps(row) + "\n")
            fh.flush()


if __name__ == "__main__":
    main()
