"""Where the compiled kernels' numba cache lives, and the stamp that keeps it true to the source.

numba keys a cached kernel on the SHA-256 of its own file alone, yet compiles into it the
kernels it calls in other modules and the constants it reads from them: ``kernels.py``'s
``fit_passes`` calls ``kernels_sample``'s ``sample_normals`` and reads ``kernel_layout``'s
constants, ``kernels_track.py`` reads ``motion_models``'. After an upgrade that changed only
such a module, the callers would load their old machine code from a kept cache (a service's
``NUMBA_CACHE_DIR`` under ``/var/lib/dffd``) and run it. So the cache directory carries a stamp,
the SHA-256 of every file whose text is compiled into a kernel (:data:`KERNEL_SOURCES`):
importing the kernels (:mod:`dffd.core.kernel_jit`) first deletes the kernels' cache files in a
directory whose stamp is another one (:func:`refresh_cache`) and writes this one, and the warm
check of :mod:`dffd.cli.loading` (is there machine code to load, or will it compile?) reads it.

The cache directory is the one numba picks: ``NUMBA_CACHE_DIR``'s, else the package's
``__pycache__`` when it can be written (numba's in-tree locator), else the user's cache.

Light on purpose (no numba, no NumPy): ``dffd --help`` and the warm check import it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

__all__ = [
    "COMPILED_MODULES",
    "CORE_DIR",
    "KERNEL_SOURCES",
    "STAMP_FILE",
    "kernel_cache_dir",
    "kernel_cache_dirs",
    "refresh_cache",
    "sources_digest",
    "stamp_current",
]

# abspath, not resolve(): numba does not resolve symlinks either.
CORE_DIR = Path(os.path.abspath(Path(__file__).parent))  # noqa: PTH100
# The modules whose @_jit functions numba compiles and caches (tests/test_kernel_cache.py checks
# this is every one of dffd/core); all in CORE_DIR, so in one cache directory.
COMPILED_MODULES = (
    "kernels.py",
    "kernels_sample.py",
    "kernels_acquire.py",
    "kernels_edges.py",
    "kernels_track.py",
    "kernels_stats.py",
)
# Every file whose text ends up in a kernel's machine code: the compiled modules, the modules
# whose constants they read (the same test checks their imports), and the compile options.
KERNEL_SOURCES = (*COMPILED_MODULES, "kernel_layout.py", "motion_models.py", "kernel_jit.py")
# In the cache directory, next to numba's files: the digest of KERNEL_SOURCES they were made of.
STAMP_FILE = "dffd-kernels.stamp"
# numba's files of the compiled modules (``<module>.<function>-<line>.py<XY>[.<n>].nb[ic]``).
_CACHE_GLOBS = ("kernels*.nbi", "kernels*.nbc")
# numba's user-wide cache (appdirs' user_cache_dir for appname "numba" on Linux).
_USER_CACHE = Path("~/.cache/numba")


def sources_digest() -> str:
    """SHA-256 (hex) of :data:`KERNEL_SOURCES`' names and texts, in that order."""
    digest = hashlib.sha256()
    for name in KERNEL_SOURCES:
        text = (CORE_DIR / name).read_bytes()
        digest.update(f"{name}\0{len(text)}\0".encode())
        digest.update(text)
    return digest.hexdigest()


def kernel_cache_dirs(environ: dict[str, str] | None = None) -> list[Path]:
    """The directories numba may keep the kernels' cache in, in numba's order of preference."""
    env = os.environ if environ is None else environ
    # numba's _CacheLocator.get_suitable_cache_subpath: "<parent dir>_<sha1 of the dir path>".
    digest = hashlib.sha1(str(CORE_DIR).encode()).hexdigest()  # noqa: S324 - numba's naming
    hashed = f"{CORE_DIR.name}_{digest}"
    if env.get("NUMBA_CACHE_DIR"):  # numba then uses that directory alone
        return [Path(env["NUMBA_CACHE_DIR"]) / hashed]
    return [CORE_DIR / "__pycache__", _USER_CACHE.expanduser() / hashed]


def kernel_cache_dir(environ: dict[str, str] | None = None) -> Path:
    """The directory numba will use for the kernels' cache: ``NUMBA_CACHE_DIR``'s, else the
    package's ``__pycache__`` if it can be written (numba's in-tree locator), else the user's."""
    dirs = kernel_cache_dirs(environ)
    if len(dirs) == 1:
        return dirs[0]
    in_tree = dirs[0]
    probe = in_tree if in_tree.is_dir() else in_tree.parent
    return in_tree if os.access(probe, os.W_OK) else dirs[1]


def stamp_current(cache: Path, digest: str | None = None) -> bool:
    """True when ``cache``'s stamp is ``digest`` (default: this source's)."""
    try:
        stamp = (cache / STAMP_FILE).read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return False
    return stamp == (sources_digest() if digest is None else digest)


def refresh_cache(cache: Path | None = None, digest: str | None = None) -> int:
    """Delete the compiled modules' cache files in ``cache`` (default: numba's directory for
    them) unless its stamp is ``digest`` (default: this source's), then write the stamp; the
    number of files deleted. A directory that cannot be written is left alone: numba compiles
    in memory then (:func:`dffd.core.kernel_jit.jit`).
    """
    directory = kernel_cache_dir() if cache is None else cache
    want = sources_digest() if digest is None else digest
    if stamp_current(directory, want):
        return 0
    deleted = 0
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for pattern in _CACHE_GLOBS:
            for path in directory.glob(pattern):
                # another process may be clearing the same directory
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                    deleted += 1
        # written whole and renamed: a process starting now reads the old stamp or this one
        part = directory / f"{STAMP_FILE}.{os.getpid()}"
        part.write_text(want + "\n", encoding="ascii")
        part.replace(directory / STAMP_FILE)
    except OSError:
        pass
    return deleted
