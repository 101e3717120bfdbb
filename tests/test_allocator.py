"""The daemon's allocator settings (dffd.daemon.allocator): glibc's, unless the user chose."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from pathlib import Path

import pytest

from dffd.daemon import allocator, cli
from dffd.exitcodes import EXIT_USAGE

glibc_only = pytest.mark.skipif(
    not sys.platform.startswith("linux") or allocator._glibc() is None, reason="glibc only"
)


@glibc_only
def test_configure_applies_on_glibc() -> None:
    assert allocator.configure({}) is True


@pytest.mark.parametrize(
    "env",
    [
        {"MALLOC_ARENA_MAX": "4"},
        {"MALLOC_TRIM_THRESHOLD_": "131072"},
        {"GLIBC_TUNABLES": "glibc.malloc.arena_max=0"},
    ],
)
def test_a_users_own_allocator_settings_are_kept(env: dict[str, str]) -> None:
    assert allocator.configure(env) is False


@glibc_only
def test_unrelated_tunables_do_not_count_as_a_choice() -> None:
    assert allocator.configure({"GLIBC_TUNABLES": "glibc.rtld.optional_static_tls=512"}) is True


def test_dffd_run_configures_the_allocator_before_anything_else(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # However the daemon is started (systemd unit, `dffd run`, `make run`), it goes through
    # dffd.daemon.cli.run: the settings apply there, even when the run then stops at once.
    calls: list[Mapping[str, str] | None] = []

    def configure(environ: Mapping[str, str] | None = None) -> bool:
        calls.append(environ)
        return True

    monkeypatch.setattr(allocator, "configure", configure)
    args = argparse.Namespace(
        config=tmp_path / "missing.toml", no_console=True, duration=None, sim_faults=None
    )
    assert cli.run(args) == EXIT_USAGE
    assert calls == [None]
