"""The tracker's kernels come compiled ahead: a cache report and the warm-up command."""

from __future__ import annotations

import numba
import pytest

from dffd import warmup
from dffd.core import kernels, kernels_acquire, kernels_sample, kernels_stats, kernels_track


def _n_kernels() -> int:
    # kernels re-exports the samples', the statistics', the 3D tracker's and the acquisition's
    # kernels; their private helpers (and kernels_sample.sample_u8) live in their own modules
    dispatchers = {
        id(v)
        for module in (kernels, kernels_acquire, kernels_sample, kernels_stats, kernels_track)
        for v in vars(module).values()
        if isinstance(v, numba.core.dispatcher.Dispatcher)
    }
    return len(dispatchers)


def test_every_kernel_is_compiled_once_and_cached() -> None:
    report = kernels.cache_report()
    assert report.kernels == _n_kernels() > 0
    assert report.uncached == 0  # the test tree's __pycache__ (or NUMBA_CACHE_DIR) is writable
    assert report.loaded + report.compiled == report.kernels
    assert report.cache_dirs


def test_warmup_reports_the_cache(capsys: pytest.CaptureFixture[str]) -> None:
    assert warmup.main([]) == warmup.EXIT_OK
    out = capsys.readouterr().out
    assert f"{_n_kernels()} kernels ready" in out
    assert kernels.cache_report().cache_dirs[0] in out


def test_warmup_says_it_compiles_before_a_cold_start(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # a first `make setup` compiles for a minute or more: the user is told before it starts
    from dffd.cli import loading

    monkeypatch.setattr(loading, "kernels_warm", lambda: False)
    assert warmup.main([]) == warmup.EXIT_OK
    first, *_ = capsys.readouterr().out.splitlines()
    assert "compiling the tracker's kernels" in first
    monkeypatch.setattr(loading, "kernels_warm", lambda: True)
    assert warmup.main([]) == warmup.EXIT_OK
    assert "compiling" not in capsys.readouterr().out
