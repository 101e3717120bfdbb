"""The kernels' numba cache is deleted when any source compiled into a kernel changed."""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

from dffd.core.kernel_cache import (
    COMPILED_MODULES,
    CORE_DIR,
    KERNEL_SOURCES,
    STAMP_FILE,
    kernel_cache_dir,
    refresh_cache,
    sources_digest,
    stamp_current,
)

# A fresh interpreter importing numba and compiling one tiny kernel: well under this when loaded.
RUN_TIMEOUT_S = 120.0


def test_the_stamp_covers_every_compiled_module_and_what_they_import() -> None:
    compiled = {p.name for p in CORE_DIR.glob("*.py") if "\n@_jit(" in p.read_text()}
    assert compiled == set(COMPILED_MODULES)
    for name in COMPILED_MODULES:
        tree = ast.parse((CORE_DIR / name).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "dffd.core":
                imported = [f"{alias.name}.py" for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dffd."):
                imported = [f"{(node.module or '').removeprefix('dffd.core.')}.py"]
            else:
                continue
            for module in imported:
                assert module in KERNEL_SOURCES, f"{name} imports {module}"


def test_a_cache_of_other_sources_is_deleted_and_stamped(tmp_path: Path) -> None:
    cache = tmp_path / "core_0123"
    cache.mkdir()
    kernel_files = [
        "kernels.fit_passes-595.py311.nbi",
        "kernels.fit_passes-595.py311.1.nbc",
        "kernels_track.track_predict-184.py311.nbi",
    ]
    for name in [*kernel_files, "step.cpython-311.pyc"]:
        (cache / name).write_bytes(b"x")
    (cache / STAMP_FILE).write_text("old\n")
    assert refresh_cache(cache, "new") == len(kernel_files)
    assert sorted(p.name for p in cache.iterdir()) == [STAMP_FILE, "step.cpython-311.pyc"]
    assert stamp_current(cache, "new")
    assert not stamp_current(cache, "old")
    # stamped: what numba writes now is kept
    (cache / kernel_files[0]).write_bytes(b"y")
    assert refresh_cache(cache, "new") == 0
    assert (cache / kernel_files[0]).exists()
    # a directory numba has not made yet is made and stamped (no second compile at the next start)
    fresh = tmp_path / "cache" / "core_4567"
    assert refresh_cache(fresh, "new") == 0
    assert stamp_current(fresh, "new")


def test_a_cache_directory_that_cannot_be_made_is_left_alone(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert refresh_cache(blocker / "core_0123", "new") == 0  # no exception: numba copes
    assert not stamp_current(blocker / "core_0123", "new")


def test_importing_the_kernels_stamps_their_cache() -> None:
    importlib.import_module("dffd.core.kernels")
    assert stamp_current(kernel_cache_dir())
    assert stamp_current(kernel_cache_dir(), sources_digest())


def test_numba_runs_a_callers_old_code_after_its_callee_changed_until_the_stamp_deletes_it(
    tmp_path: Path,
) -> None:
    """Why the stamp exists: numba keys a cached kernel on its own file, not its callees'."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    callee = package / "kernels_callee.py"
    callee.write_text(
        "import numba\nSCALE = 2\n\n\n@numba.njit(cache=True)\ndef callee(x):\n"
        "    return x * SCALE\n"
    )
    (package / "kernels_caller.py").write_text(
        "import numba\nfrom pkg.kernels_callee import callee\n\n\n@numba.njit(cache=True)\n"
        "def caller(x):\n    return callee(x) + 1\n"
    )
    numba_cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(numba_cache), "PYTHONPATH": str(tmp_path)}

    def caller_of_ten() -> int:
        out = subprocess.run(
            [sys.executable, "-c", "from pkg.kernels_caller import caller; print(caller(10))"],
            env=env,
            cwd=tmp_path,
            capture_output=True,
            text=True,
            check=True,
            timeout=RUN_TIMEOUT_S,
        )
        return int(out.stdout)

    assert caller_of_ten() == 21
    callee.write_text(callee.read_text().replace("SCALE = 2", "SCALE = 3"))
    assert caller_of_ten() == 21  # the caller's cached machine code still has SCALE = 2
    (cache,) = list(numba_cache.iterdir())  # numba's "<dir>_<sha1 of the dir>" subdirectory
    assert refresh_cache(cache, "the sources' new digest") > 0
    assert caller_of_ten() == 31
