"""How every compiled kernel is compiled and cached (numba, ``nogil``), and the cache report.

Shared by the contour tracker's kernels (:mod:`dffd.core.kernels`) and the 3D tracker's
(:mod:`dffd.core.kernels_track`): importing a kernel module compiles (or loads) its kernels.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import numba

from dffd.core.kernel_cache import kernel_cache_dir, refresh_cache

__all__ = ["CacheReport", "cache_report", "jit"]

_F = TypeVar("_F", bound=Callable[..., Any])

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class CacheReport:
    """Where the kernels' machine code came from in this process."""

    kernels: int  # compiled dispatchers
    loaded: int  # loaded from the cache
    compiled: int  # compiled now (cache miss: first run after an install or a source change)
    uncached: int  # compiled in memory because no cache directory was writable
    cache_dirs: tuple[str, ...]  # where the cache lives (empty when uncached)


def cache_report() -> CacheReport:
    """How this process got its kernels (the kernels compile when their module is imported)."""
    loaded = sum(sum(k.stats.cache_hits.values()) for k in _KERNELS)
    missed = sum(sum(k.stats.cache_misses.values()) for k in _KERNELS)
    dirs = sorted({str(k.stats.cache_path) for k in _KERNELS if k.stats.cache_path})
    return CacheReport(
        kernels=len(_KERNELS),
        loaded=loaded,
        compiled=missed + len(_UNCACHED),
        uncached=len(_UNCACHED),
        cache_dirs=tuple(dirs),
    )


def jit(signature: str, *, contract: bool = False) -> Callable[[_F], _F]:
    """Compile ``fn`` now for exactly ``signature`` (no compilation on a later call).

    ``contract``: let LLVM fuse ``a * b + c`` into one fused multiply-add where the CPU has
    one (and only that: no other fast-math licence), as OpenCV's SIMD code does.

    ``cache=True`` reuses the machine code across processes (tests, daemon restarts) from
    ``NUMBA_CACHE_DIR``, else ``__pycache__`` next to the kernel's file, else ``~/.cache``;
    numba raises when none is writable (a read-only install without a state directory):
    compile in memory then — it only costs start-up time (~15-20 s of CPU). numba keys a cached
    kernel on its own file's source alone, yet compiles into it the kernels it calls and the
    constants it reads from other modules: this module's import deletes a cache made of other
    sources first (:mod:`dffd.core.kernel_cache`).
    """

    fastmath: bool | set[str] = {"contract"} if contract else False

    def compile_now(fn: _F) -> _F:
        try:
            kernel = numba.njit(cache=True, nogil=True, fastmath=fastmath)(fn)
        except RuntimeError as exc:
            if not _UNCACHED:
                logger.warning(
                    "numba cache not writable (%s): the tracker's kernels are compiled in "
                    "memory at every start (~15 s); set NUMBA_CACHE_DIR to a writable "
                    "directory and run `python -m dffd.warmup` once",
                    exc,
                )
            _UNCACHED.append(fn.__name__)
            kernel = numba.njit(cache=False, nogil=True, fastmath=fastmath)(fn)
        kernel.compile(signature)
        kernel.disable_compile()
        _KERNELS.append(kernel)
        return cast(_F, kernel)

    return compile_now


_KERNELS: list[Any] = []  # every compiled dispatcher, for cache_report()
_UNCACHED: list[str] = []  # kernels compiled without a cache
# Before any kernel of this process is loaded: a cache compiled from other sources (an upgrade
# that changed only a callee or a constant's module) would be loaded as it is by numba.
# numba's own reading of NUMBA_CACHE_DIR (at its import) decides the directory.
_NUMBA_CACHE_DIR: str = getattr(numba.config, "CACHE_DIR", "")
_STALE_DELETED = refresh_cache(
    kernel_cache_dir({"NUMBA_CACHE_DIR": _NUMBA_CACHE_DIR} if _NUMBA_CACHE_DIR else {})
)
if _STALE_DELETED:
    logger.info(
        "deleted %d cached kernel files compiled from other sources: the kernels compile once",
        _STALE_DELETED,
    )
