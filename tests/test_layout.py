"""The package layout's rules: no import cycles, drivers never imports dffd, a pure core.

Each check imports modules in a fresh interpreter (a module already imported by another test
would hide a cycle or a stray dependency).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
# Importing every module of the three packages once in a fresh interpreter (OpenCV, SciPy and
# numba included): ~10 s on the 2-core dev machine under load.
IMPORT_TIMEOUT_S = 120.0
PACKAGES = ("dffd", "drivers", "hil")


def _modules(package: str) -> list[str]:
    root = REPO / package
    names = []
    for path in sorted(root.rglob("*.py")):
        if path.name == "__main__.py":  # runs the CLI when imported
            continue
        parts = path.relative_to(REPO).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def _probe(code: str) -> object:
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=IMPORT_TIMEOUT_S,
        check=False, cwd=REPO,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("package", PACKAGES)
def test_every_module_imports_in_a_fresh_interpreter(package: str) -> None:
    # Importing each module first in its own interpreter would catch every cycle but costs one
    # interpreter per module; importing them in sorted order in one interpreter catches a cycle
    # that breaks whichever module of the cycle comes first.
    names = _modules(package)
    failed = _probe(
        "import importlib, json\n"
        "failed = []\n"
        f"for name in {names!r}:\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except Exception as exc:\n"
        "        failed.append(f'{name}: {exc!r}')\n"
        "print(json.dumps(failed))\n"
    )
    assert failed == []


def test_drivers_never_import_dffd_or_hil() -> None:
    names = _modules("drivers")
    loaded = _probe(
        "import importlib, json, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('dffd', 'hil'))))\n"
    )
    assert loaded == []


@pytest.mark.parametrize("package", ["dffd.core", "dffd.scheduler"])
def test_core_and_scheduler_import_no_asyncio_daemon_or_io_layers(package: str) -> None:
    names = [n for n in _modules("dffd") if n == package or n.startswith(package + ".")]
    loaded = _probe(
        "import importlib, json, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "bad = ('asyncio', 'dffd.daemon', 'dffd.mqtt', 'dffd.config', 'aiomqtt', 'serial')\n"
        "print(json.dumps(sorted(m for m in sys.modules\n"
        "                        if any(m == b or m.startswith(b + '.') for b in bad))))\n"
    )
    assert loaded == []
