"""What a user is told while a command that needs the estimation core is still loading.

Loading the core takes a few seconds (NumPy, SciPy, OpenCV, numba and the tracker's compiled
kernels); on the first start after an install or upgrade numba compiles those kernels instead,
~20-40 s of CPU with nothing on the screen. Before importing anything heavy this looks for the
kernels' numba cache where numba will look for it (:func:`dffd.core.kernel_cache.kernel_cache_dir`)
and, when it is not warm, says that the kernels compile now and how to do it ahead.

"Warm" (:func:`kernels_warm`) is checked without importing numba and without unpickling: the
cache directory's stamp is the digest of today's kernel sources (else importing the kernels
deletes their cache files: :mod:`dffd.core.kernel_cache`), and every kernel of the compiled
modules (``kernels.py``, ``kernels_track.py``, …: ``COMPILED_MODULES``) has its index file
(``<module>.<name>-<line>.py<XY>.nbi``, the name numba gives it) written by this numba version
(the version string that opens the file) for this very source (numba stamps the index with the
SHA-256 of the source file; the digest's bytes are looked up in the file) and at least one data
file. What it cannot see: an index written on another CPU model (numba keys its entries by the
CPU as well); numba then compiles on first use.
"""

from __future__ import annotations

import hashlib
import re
import sys
from importlib import metadata
from pathlib import Path

from dffd.core.kernel_cache import (
    COMPILED_MODULES,
    CORE_DIR,
    kernel_cache_dir,
    kernel_cache_dirs,
    stamp_current,
)

__all__ = ["kernels_cached", "kernels_warm", "say_if_compiling"]


def kernels_cached(environ: dict[str, str] | None = None) -> bool:
    """True when an index file of the kernels' numba cache exists in one of those places."""
    return any(any(d.glob("kernels.*.nbi")) for d in kernel_cache_dirs(environ) if d.is_dir())


def kernels_warm(environ: dict[str, str] | None = None) -> bool:
    """True when numba will load every kernel from its cache instead of compiling it (see the
    module docstring for what is checked)."""
    try:
        version = metadata.version("numba").encode()
    except metadata.PackageNotFoundError:
        return False
    cache = kernel_cache_dir(environ)
    if not stamp_current(cache):  # made of other sources: importing the kernels deletes it
        return False
    tag = f"py{sys.version_info[0]}{sys.version_info[1]}"
    for module in COMPILED_MODULES:
        try:
            text = (CORE_DIR / module).read_bytes()
        except OSError:
            return False
        stamp = hashlib.sha256(text).digest()
        names = _kernel_names(text.decode("utf-8", errors="replace"), module.removesuffix(".py"))
        if not names or not all(
            _index_fresh(cache, f"{name}.{tag}", version, stamp) for name in names
        ):
            return False
    return True


def say_if_compiling(command: str, *, background: bool = False) -> None:
    """Tell the user on stderr when ``dffd COMMAND`` is about to compile the kernels.

    ``background``: the command runs on the kernels' NumPy twins while they compile.
    """
    if kernels_warm():
        return
    what = (
        "the tracker's kernels compile in the background (~20-40 s of CPU, once); it runs on "
        "their slower NumPy twins meanwhile"
        if background
        else "compiling the tracker's kernels (~20-40 s, once; `python -m dffd.warmup` does it "
        "ahead, `make setup` runs it)…"
    )
    print(f"dffd {command}: first start after an install: {what}", file=sys.stderr, flush=True)


# A kernel of a compiled module: the ``@_jit(`` line (numba names the cache by the first line of
# the decorated function, decorator included) and the function name that follows it.
_KERNEL_RE = re.compile(r"^@_jit\(.*?^def (\w+)\(", re.MULTILINE | re.DOTALL)
# The numba version string is pickled at the very start of an index file.
_VERSION_HEAD_BYTES = 64


def _kernel_names(source: str, stem: str) -> list[str]:
    """numba's cache file stems of the kernels of module ``stem``: ``<stem>.<name>-<line>``."""
    names = []
    for match in _KERNEL_RE.finditer(source):
        line = source.count("\n", 0, match.start()) + 1
        names.append(f"{stem}.{match.group(1)}-{line}")
    return names


def _index_fresh(cache: Path, base: str, version: bytes, stamp: bytes) -> bool:
    """``base``.nbi was written by this numba for this source, and a data file exists."""
    try:
        data = (cache / f"{base}.nbi").read_bytes()
    except OSError:
        return False
    if version not in data[:_VERSION_HEAD_BYTES] or stamp not in data:
        return False
    return any(cache.glob(f"{base}.*.nbc"))
