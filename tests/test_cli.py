"""The ``dffd`` command line: one table of subcommands, one set of exit codes, light --help."""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dffd import exitcodes
from dffd.cli import SUBCOMMANDS, build_parser, service_log_level, verbosity_level
from dffd.cli.arguments import REPLAY_ESTIMATORS
from dffd.resources import default_config_file

KERNELS_SOURCE = Path(__file__).resolve().parent.parent / "dffd/core/kernels.py"
# A fresh interpreter running `dffd X --help` (imports only): well under this on a loaded machine.
HELP_TIMEOUT_S = 30.0
# Modules whose import takes 0.05-2 s each (asyncio and the VISCA codec ~0.05 s: `sim-camera
# --help` took 0.3-0.47 s with them and the simulated device); none is needed to print help.
HEAVY = (
    "cv2", "scipy", "numba", "matplotlib", "numpy", "pydantic", "aiomqtt", "amqtt", "asyncio",
    "serial", "aiohttp",
)  # fmt: skip


@pytest.mark.parametrize("command", [None, *SUBCOMMANDS])
def test_help_imports_nothing_heavy(command: str | None) -> None:
    argv = [] if command is None else [command]
    probe = (
        "import json, sys\n"
        "from dffd.cli import main\n"
        "try:\n"
        f"    main({[*argv, '--help']!r})\n"
        "except SystemExit as exc:\n"
        "    assert exc.code == 0, exc.code\n"
        f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=HELP_TIMEOUT_S,
        check=True,
    )  # fmt: skip
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert loaded == [], f"dffd {command} --help imports {loaded}"


def test_every_subcommand_has_arguments_and_an_implementation() -> None:
    for name, sub in SUBCOMMANDS.items():
        parser = build_parser(name)  # loads the arguments, never the implementation
        assert parser.prog == "dffd"
        module, _, function = sub.implementation.partition(":")
        assert callable(getattr(importlib.import_module(module), function)), name


def test_the_command_lines_verbosity_wins_over_the_configured_level_when_it_asks_for_more() -> None:
    assert [verbosity_level(n) for n in range(4)] == [
        logging.WARNING, logging.INFO, logging.DEBUG, logging.DEBUG,
    ]  # fmt: skip
    # no -v: [log] level alone
    assert service_log_level("INFO", 0) == logging.INFO
    assert service_log_level("ERROR", 0) == logging.ERROR
    # -vv: DEBUG, whatever [log] level says (the timeline of docs/design.md §5.3)
    assert service_log_level("INFO", 2) == logging.DEBUG
    assert service_log_level("ERROR", 2) == logging.DEBUG
    # -v: INFO over a quieter level, and never quieter than the configured one
    assert service_log_level("WARNING", 1) == logging.INFO
    assert service_log_level("DEBUG", 1) == logging.DEBUG


# A fresh interpreter running `dffd check-config` (pydantic, no kernels): well under this.
CHECK_CONFIG_TIMEOUT_S = 60.0


@pytest.mark.parametrize("unbuffered", [True, False])
def test_a_reader_that_closed_the_pipe_early_gets_no_traceback(unbuffered: bool) -> None:
    """`dffd check-config --json | head -1`: once head has exited, dffd's output has nowhere to
    go. A real pipe whose reader is gone before dffd writes: exit 1 (as Python exits on EPIPE),
    nothing on stderr. Unbuffered (PYTHONUNBUFFERED=1), the subcommand's print fails (it was a
    traceback); buffered, the flush at the end (it was Python's "Exception ignored", exit 120)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "dffd", "check-config", "--json", str(default_config_file())],
            stdout=write_end, stderr=subprocess.PIPE, text=True, env=env,
            timeout=CHECK_CONFIG_TIMEOUT_S, check=False,
        )  # fmt: skip
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr) == (exitcodes.EXIT_FAILURE, "")


def test_driver_tools_use_the_same_exit_codes() -> None:
    # drivers never imports dffd, so its two subcommands keep constants of their own.
    from drivers import usb
    from drivers.sim import cli as sim_cli

    for module in (sim_cli, usb):
        for name in ("EXIT_OK", "EXIT_FAILURE", "EXIT_USAGE"):
            if hasattr(module, name):
                assert getattr(module, name) == getattr(exitcodes, name), (module, name)


def test_light_copies_of_implementation_constants_match() -> None:
    from dffd.cli import arguments
    from dffd.core.pipeline import ESTIMATORS
    from drivers import usb

    assert tuple(REPLAY_ESTIMATORS) == tuple(ESTIMATORS)
    assert arguments.DEVICES_LINK_NAME == usb.DEFAULT_LINK_NAME
    assert arguments.DEVICES_GROUP == usb.DEFAULT_GROUP
    assert arguments.DEVICES_SYSFS == usb.SYSFS_USB


def test_a_first_start_says_the_kernels_compile(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from dffd.cli.loading import kernels_cached, say_if_compiling
    from dffd.core.kernel_cache import kernel_cache_dirs

    warm = _copy_of_the_warm_cache(tmp_path / "warm")
    env = {"NUMBA_CACHE_DIR": str(tmp_path)}
    assert not kernels_cached(env)
    (cache,) = kernel_cache_dirs(env)
    assert cache.parent == tmp_path
    assert cache.name.startswith("core_")  # numba's "<dir>_<sha1 of the dir>" naming
    cache.mkdir()
    (cache / "kernels._kernel_irls-261.py311.nbi").write_bytes(b"")
    assert kernels_cached(env)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    say_if_compiling("run")  # an index file that is not this numba's for this source: not warm
    assert "compiling the tracker's kernels" in capsys.readouterr().err
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(warm))
    say_if_compiling("run")
    assert capsys.readouterr().err == ""


def test_the_kernels_are_warm_only_with_a_fresh_index_of_every_kernel(tmp_path: Path) -> None:
    """What decides whether ``dffd run`` spawns the warm-up process (dffd.warmup)."""
    from dffd.cli.loading import kernels_warm
    from dffd.core.kernel_cache import STAMP_FILE, kernel_cache_dir

    importlib.import_module("dffd.core.kernels")  # loads (or compiles and caches) them
    assert kernels_warm()
    assert not kernels_warm({"NUMBA_CACHE_DIR": str(tmp_path / "empty")})
    root = _copy_of_the_warm_cache(tmp_path / "copy")
    env = {"NUMBA_CACHE_DIR": str(root)}
    assert kernels_warm(env)
    cache = kernel_cache_dir(env)
    digest = hashlib.sha256(KERNELS_SOURCE.read_bytes()).digest()
    # this source's index files (a cache also keeps those of earlier sources: other names)
    indexes = sorted(i for i in cache.glob("kernels.*.nbi") if digest in i.read_bytes())
    stale = indexes[0].read_bytes()
    indexes[0].write_bytes(stale.replace(digest, bytes(len(digest))))  # another source's
    assert not kernels_warm(env)
    indexes[0].write_bytes(stale)
    assert kernels_warm(env)
    # every compiled module's kernels count (dffd/core/kernels_*.py)
    for name in (
        "kernels_sample",
        "kernels_acquire",
        "kernels_edges",
        "kernels_stats",
        "kernels_track",
    ):
        other_digest = hashlib.sha256(KERNELS_SOURCE.with_name(f"{name}.py").read_bytes()).digest()
        other = sorted(i for i in cache.glob(f"{name}.*.nbi") if other_digest in i.read_bytes())
        other_index = other[0].read_bytes()
        other[0].write_bytes(other_index.replace(other_digest, bytes(len(other_digest))))
        assert not kernels_warm(env), name
        other[0].write_bytes(other_index)
        assert kernels_warm(env)
    # a cache stamped with other kernel sources (a callee's or a constant's module changed):
    # importing the kernels deletes it, so it is not warm
    stamp = (cache / STAMP_FILE).read_bytes()
    (cache / STAMP_FILE).write_text("0" * 64 + "\n")
    assert not kernels_warm(env)
    (cache / STAMP_FILE).write_bytes(stamp)
    assert kernels_warm(env)
    for data in cache.glob(indexes[-1].name.removesuffix(".nbi") + ".*.nbc"):
        data.unlink()  # an index without its machine code
    assert not kernels_warm(env)


def _copy_of_the_warm_cache(root: Path) -> Path:
    """A NUMBA_CACHE_DIR holding a copy of the kernels' warm cache (call it before changing
    NUMBA_CACHE_DIR: numba reads it once)."""
    from dffd.core.kernel_cache import kernel_cache_dir, kernel_cache_dirs

    importlib.import_module("dffd.core.kernels")  # loads (or compiles and caches) them
    (target,) = kernel_cache_dirs({"NUMBA_CACHE_DIR": str(root)})
    shutil.copytree(kernel_cache_dir(), target)
    return root
