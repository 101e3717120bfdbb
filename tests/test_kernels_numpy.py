"""The kernels' NumPy twins give the compiled kernels' results on the same inputs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from dffd.core import kernel_dispatch, kernels, kernels_numpy
from dffd.core.contour import (
    BoundaryObservation,
    ContourTracker,
    Motion,
    TrackerConfig,
    find_target,
)
from dffd.core.kernel_layout import S_TMP, S_TMP2, S_WNEW
from dffd.core.synthetic import render_disc

W, H = 640, 480
REPO = Path(__file__).resolve().parent.parent
# Rounding: both run the same float32/float64 operations, only in another order (NumPy's pairwise
# sums, LAPACK's solve against the kernel's elimination); the NumPy reference test asserts 1e-9.
RTOL = 1e-9
# A fresh interpreter that loads the cached kernels in a warm-up process: a few seconds.
SWAP_TIMEOUT_S = 120.0
# scratch rows the kernels use as private temporaries (the twins do not write them)
PRIVATE_ROWS = (S_TMP, S_TMP2, S_WNEW)


class _Recorder:
    """The compiled kernels, keeping a copy of every call's inputs."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple[Any, ...]]] = []

    def _call(self, name: str, args: tuple[Any, ...]) -> Any:
        self.calls.append((name, _copy(args)))
        return getattr(kernels, name)(*args)

    def normals_and_box(self, *args: Any) -> Any:
        return self._call("normals_and_box", args)

    def sample_maps(self, *args: Any) -> None:
        self._call("sample_maps", args)

    def fit_pass(self, *args: Any) -> None:
        self._call("fit_pass", args)

    def edge_moments(self, *args: Any) -> None:
        self._call("edge_moments", args)


def test_every_kernel_call_of_a_tracked_sequence_gives_the_same_outputs() -> None:
    recorder = _Recorder()
    with kernel_dispatch.using(recorder):
        for motion in ("similarity", "affine", "translation"):
            _track(motion)
    names = {name for name, _ in recorder.calls}
    assert names == {"normals_and_box", "sample_maps", "fit_pass", "edge_moments"}
    lost = 0
    for name, args in recorder.calls:
        fast, twin = _copy(args), _copy(args)
        got_fast = getattr(kernels, name)(*fast)
        got_twin = getattr(kernels_numpy, name)(*twin)
        if name == "normals_and_box":
            np.testing.assert_allclose(got_twin, got_fast, rtol=RTOL)
        if name == "fit_pass":  # the scratch array holds both kernels' temporaries
            lost += int(fast[-1][0] != 0)
            for row in PRIVATE_ROWS:
                fast[15][row] = twin[15][row] = 0.0
        for a, b in zip(twin, fast, strict=True):
            if isinstance(a, np.ndarray):
                np.testing.assert_allclose(a, b, rtol=RTOL, atol=1e-12, err_msg=name)
    assert 0 < lost < len(recorder.calls)  # both branches of the pass: found and lost


def test_the_tracker_follows_the_same_contour_with_either_implementation() -> None:
    for motion in ("similarity", "affine"):
        fast = _track(motion)
        with kernel_dispatch.using(kernels_numpy):
            twin = _track(motion)
        costs = 0
        for (a, cost_a), (b, cost_b) in zip(twin, fast, strict=True):
            assert a.ok == b.ok
            assert a.r_px == pytest.approx(b.r_px, rel=RTOL)
            np.testing.assert_allclose(a.points, b.points, rtol=RTOL)
            assert (cost_a is None) == (cost_b is None)
            if cost_a is not None and cost_b is not None:
                assert cost_a == pytest.approx(cost_b, rel=RTOL)
                costs += 1
        assert costs > 20


def test_a_background_warm_up_swaps_the_compiled_kernels_in() -> None:
    code = (
        "from dffd import warmup\n"
        "from dffd.core import kernel_dispatch as d\n"
        "w = warmup.start_background()\n"
        "assert d.active() == 'numpy', d.active()\n"
        f"assert w.done.wait({SWAP_TIMEOUT_S}), 'no swap'\n"
        "print(d.active())\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=SWAP_TIMEOUT_S + 30,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "compiled"


def test_a_warm_cache_spawns_no_warm_up_process(tmp_path: Path) -> None:
    """With the kernels cached the service loads them in a thread; a cold cache spawns
    ``python -m dffd.warmup`` (stopped here at once: only the decision is tested)."""
    kernels.cache_report()  # imported above: the cache of this tree is warm
    code = (
        "import logging, sys\n"
        "logging.basicConfig(level=logging.INFO, stream=sys.stdout, format='%(message)s')\n"
        "from dffd import warmup\n"
        "from dffd.core import kernel_dispatch as d\n"
        "w = warmup.start_background()\n"
        "print('spawn', w.spawn)\n"
        "if w.spawn:\n"
        "    w.stop()\n"
        f"assert w.done.wait({SWAP_TIMEOUT_S}), 'no swap'\n"
        "print(d.active())\n"
    )
    runs = {}
    for name, extra in (("warm", {}), ("cold", {"NUMBA_CACHE_DIR": str(tmp_path)})):
        env = {**os.environ, "PYTHONPATH": str(REPO), **extra}
        proc = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True,
            timeout=SWAP_TIMEOUT_S + 30, check=False,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        runs[name] = proc.stdout
    assert "spawn False" in runs["warm"]
    assert "loaded from numba's cache" in runs["warm"]
    assert runs["warm"].strip().endswith("compiled")
    assert "spawn True" in runs["cold"]


def test_the_twins_import_no_compiler() -> None:
    code = "import sys, dffd.core.contour\nprint('numba' in sys.modules)\n"
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert proc.stdout.strip() == "False"


def _track(motion: Motion) -> list[tuple[BoundaryObservation, tuple[float, float] | None]]:
    """A moving, growing disc with blurred frames, clutter across its edge and one lost frame."""
    rng = np.random.default_rng(21)
    tracker = ContourTracker(TrackerConfig(relax=0.2))
    img = render_disc(W, H, (300.3, 230.7), 40.0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    out = []
    for k in range(1, 30):
        c = (300.3 + 1.7 * k, 230.7 - 0.9 * k)
        img = render_disc(W, H, c, 40.0 * (1 + 0.005 * k), 3.0 if k % 5 == 0 else 0.0, rng=rng)
        if 10 <= k < 20:  # a bright bar across the right edge: outliers
            x = int(c[0] + 36)
            cv2.rectangle(img, (x, int(c[1]) - 8), (x + 30, int(c[1]) + 8), 250, -1)
        if k == 25:  # the target vanishes for a frame
            img = render_disc(W, H, (-500, -500), 40.0, 0.0, rng=rng)
        obs = tracker.update(img, k / 30, motion)
        moments = obs.edge_moments()
        out.append((obs, None if moments is None else moments.cost))
    return out


def _copy(args: tuple[Any, ...]) -> tuple[Any, ...]:
    return tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)
