"""The Makefile's targets that need no set-up, run by the real make in a scratch directory."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

MAKEFILE = Path(__file__).resolve().parent.parent / "Makefile"
# `make clean` is one rm: well under this.
MAKE_TIMEOUT_S = 30.0

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def test_make_clean_removes_what_the_build_left_and_nothing_else(tmp_path: Path) -> None:
    """setuptools reuses a stale build/lib: a module moved since the last build would be put in
    the next wheel, so clean removes build/ and *.egg-info/ with the venv and the caches."""
    made = [
        ".venv/bin/python", ".mypy_cache/x", ".ruff_cache/x", ".pytest_cache/x",
        "build/lib/dffd/moved_since.py", "dffd.egg-info/SOURCES.txt",
    ]  # fmt: skip
    kept = ["pyproject.toml", "dffd/__init__.py", "runs/log/estimates.jsonl", "hil/out/x.json"]
    for name in made + kept:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("", encoding="utf-8")
    subprocess.run(
        ["make", "-s", "-C", str(tmp_path), "-f", str(MAKEFILE), "clean"],
        check=True, timeout=MAKE_TIMEOUT_S,
    )  # fmt: skip
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    assert left == sorted(kept)
    assert not (tmp_path / "build").exists()
    assert not (tmp_path / "dffd.egg-info").exists()
