"""What a user is told while a command that needs the estimation core is still loading.

Loading the core takes a few seconds (NumPy, SciPy, OpenCV, numba and the tracker's compiled
kernels); on the first start after an install or upgrade numba compiles those kernels instead,
~20-40 s of CPU with nothing on the screen. Before importing anything heavy this looks for the
kernels' numba cache index files where numba keeps them (``NUMBA_CACHE_DIR``, the package's
``__pycache__``, the user cache) and, when there are none, says that the kernels compile now and
how to do it ahead. Checking for the files only: a cache made stale by a changed kernel source
still counts as present (numba then recompiles silently; ``python -m dffd.warmup`` reports it).
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import dffd

__all__ = ["KERNELS_MODULE", "kernel_cache_dirs", "kernels_cached", "say_if_compiling"]

# The module whose numba kernels are cached (dffd.core.kernels), relative to the package.
KERNELS_MODULE = Path("core") / "kernels.py"
# numba's user-wide cache (appdirs' user_cache_dir for appname "numba" on Linux).
_USER_CACHE = Path("~/.cache/numba")


def kernel_cache_dirs(environ: dict[str, str] | None = None) -> list[Path]:
    """The directories numba may keep the kernels' cache in, in numba's order of preference."""
    env = os.environ if environ is None else environ
    # abspath, not resolve(): numba does not resolve symlinks either.
    source = Path(os.path.abspath(Path(dffd.__file__).parent / KERNELS_MODULE))  # noqa: PTH100
    subpath = str(source.parent)
    # numba's _CacheLocator.get_suitable_cache_subpath: "<parent dir>_<sha1 of the dir path>".
    digest = hashlib.sha1(subpath.encode()).hexdigest()  # noqa: S324 - numba's naming scheme
    hashed = f"{source.parent.name}_{digest}"
    if env.get("NUMBA_CACHE_DIR"):  # numba then uses that directory alone
        return [Path(env["NUMBA_CACHE_DIR"]) / hashed]
    return [source.parent / "__pycache__", _USER_CACHE.expanduser() / hashed]


def kernels_cached(environ: dict[str, str] | None = None) -> bool:
    """True when an index file of the kernels' numba cache exists in one of those places."""
    stem = KERNELS_MODULE.stem
    return any(any(d.glob(f"{stem}.*.nbi")) for d in kernel_cache_dirs(environ) if d.is_dir())


def say_if_compiling(command: str, *, background: bool = False) -> None:
    """Tell the user on stderr when ``dffd COMMAND`` is about to compile the kernels.

    ``background``: the command runs on the kernels' NumPy twins while they compile.
    """
    if kernels_cached():
        return
    what = (
        "the tracker's kernels compile in the background (~20-40 s of CPU, once); it runs on "
        "their slower NumPy twins meanwhile"
        if background
        else "compiling the tracker's kernels (~20-40 s, once; `python -m dffd.warmup` does it "
        "ahead, `make setup` runs it)…"
    )
    print(f"dffd {command}: first start after an install: {what}", file=sys.stderr, flush=True)
