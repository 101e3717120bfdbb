"""``python -m dffd.warmup``: compile the tracker's kernels into the numba cache ahead of a start.

Run once after every install or upgrade, as the user the service runs as and with its
``NUMBA_CACHE_DIR`` (``make setup`` does it for the development tree): the first ``dffd run``
then loads machine code (~1-2 s) instead of compiling it (~15-20 s of CPU before the first
estimate). Exit 0 when the kernels are cached, 1 when no cache directory is writable (the message
says which variable to set).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

EXIT_OK = 0
EXIT_FAILURE = 1


def main(argv: Sequence[str] | None = None) -> int:
    """Compile or load every kernel, print where the cache is and how long it took."""
    parser = argparse.ArgumentParser(
        prog="python -m dffd.warmup", description=(__doc__ or "").split("\n\n", 1)[1]
    )
    parser.parse_args(argv)
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
