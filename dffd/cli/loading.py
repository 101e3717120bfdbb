"""What a user is told while a command that needs the estimation core is still loading.

Loading the core takes a few seconds (NumPy, SciPy, OpenCV, numba and the tracker's compiled
kernels); on the first start after an install or upgrade numba compiles those kernels instead,
~20-40 s of CPU with nothing on the screen. Before importing anything heavy this looks for the
kernels' numba cache where numba will look for it (``NUMBA_CACHE_DIR``, else the package's
``__pycache__`` when writable, else the user cache) and, when it is not warm, says that the
kernels compile now and how to do it ahead.

"Warm" (:func:`kernels_warm`) is checked without importing numba and without unpickling: every
kernel of ``dffd/core/kernels.py`` has its index file (``kernels.<name>-<line>.py<XY>.nbi``, the
name numba gives it) written by this numba version (the version string that opens the file) for
this very source (numba stamps the index with the SHA-256 of the source file; the digest's bytes
are looked up in the file) and at least one data file. What it cannot see: an index written on
another CPU model (numba keys its entries by the CPU as well); numba then compiles on first use.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
from importlib import metadata
from pathlib import Path

import dffd

__all__ = [
    "KERNELS_MODULE",
    "KERNEL_MODULES",
    "kernel_cache_dir",
    "kernel_cache_dirs",
    "kernels_cached",
    "kernels_warm",
    "say_if_compiling",
]

# The module whose numba kernels are cached (dffd.core.kernels), relative to the package.
KERNELS_MODULE = Path("core") / "kernels.py"
# Every module with compiled kernels (importing dffd.core.kernels imports the 3D tracker's too);
# all in the same directory, so in the same cache directory.
KERNEL_MODULES = (
    KERNELS_MODULE,
    Path("core") / "kernels_sample.py",
    Path("core") / "kernels_stats.py",
    Path("core") / "kernels_track.py",
)
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


def kernel_cache_dir(environ: dict[str, str] | None = None) -> Path:
    """The directory numba will use for the kernels' cache: ``NUMBA_CACHE_DIR``'s, else the
    package's ``__pycache__`` if it can be written (numba's in-tree locator), else the user's."""
    dirs = kernel_cache_dirs(environ)
    if len(dirs) == 1:
        return dirs[0]
    in_tree = dirs[0]
    probe = in_tree if in_tree.is_dir() else in_tree.parent
    return in_tree if os.access(probe, os.W_OK) else dirs[1]


def kernels_cached(environ: dict[str, str] | None = None) -> bool:
    """True when an index file of the kernels' numba cache exists in one of those places."""
    stem = KERNELS_MODULE.stem
    return any(any(d.glob(f"{stem}.*.nbi")) for d in kernel_cache_dirs(environ) if d.is_dir())


def kernels_warm(environ: dict[str, str] | None = None) -> bool:
    """True when numba will load every kernel from its cache instead of compiling it (see the
    module docstring for what is checked)."""
    try:
        version = metadata.version("numba").encode()
    except metadata.PackageNotFoundError:
        return False
    cache = kernel_cache_dir(environ)
    tag = f"py{sys.version_info[0]}{sys.version_info[1]}"
    for module in KERNEL_MODULES:
        source = Path(dffd.__file__).parent / module
        try:
            text = source.read_bytes()
        except OSError:
            return False
        stamp = hashlib.sha256(text).digest()
        names = _kernel_names(text.decode("utf-8", errors="replace"), module.stem)
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


# A kernel of dffd/core/kernels.py: the ``@_jit(`` line (numba names the cache by the first line of
# the decorated function, decorator included) and the function name that follows it.
_KERNEL_RE = re.compile(r"^@_jit\(.*?^def (\w+)\(", re.MULTILINE | re.DOTALL)
# The numba version string is pickled at the very start of an index file.
_VERSION_HEAD_BYTES = 64


def _kernel_names(source: str, stem: str = KERNELS_MODULE.stem) -> list[str]:
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
