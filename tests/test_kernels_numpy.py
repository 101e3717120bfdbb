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
from dffd.core.acquisition import find_target
from dffd.core.contour import BoundaryObservation, ContourTracker, Motion, TrackerConfig
from dffd.core.kernel_layout import OUT_STATUS, S_TMP, S_TMP2, S_WNEW, ST_KEPT, ST_NEED_WINDOW
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
# positions of fit_passes' state and scratch arrays among its arguments
FIT_STATE, FIT_SCRATCH, FIT_OUT = 14, 21, 23


class _Recorder:
    """The compiled kernels, keeping a copy of every call's inputs."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple[Any, ...]]] = []

    def _call(self, name: str, args: tuple[Any, ...]) -> Any:
        self.calls.append((name, _copy(args)))
        return getattr(kernels, name)(*args)

    def normals_and_box(self, *args: Any) -> Any:
        return self._call("normals_and_box", args)

    def fit_passes(self, *args: Any) -> None:
        self._call("fit_passes", args)

    def resample(self, *args: Any) -> None:
        self._call("resample", args)

    def polarity(self, *args: Any) -> Any:
        return self._call("polarity", args)

    def edge_moments(self, *args: Any) -> None:
        self._call("edge_moments", args)

    def sobel_pair(self, *args: Any) -> None:
        self._call("sobel_pair", args)

    def acquire_mask(self, *args: Any) -> Any:
        return self._call("acquire_mask", args)


def test_every_kernel_call_of_a_tracked_sequence_gives_the_same_outputs() -> None:
    recorder = _Recorder()
    with kernel_dispatch.using(recorder):
        for motion in ("similarity", "affine", "translation"):
            _track(motion)
    names = {name for name, _ in recorder.calls}
    assert names == {
        "normals_and_box", "fit_passes", "edge_moments", "resample", "polarity", "sobel_pair",
        "acquire_mask",
    }  # fmt: skip
    lost = resumed = 0
    for name, args in recorder.calls:
        fast, twin = _copy(args), _copy(args)
        got_fast = getattr(kernels, name)(*fast)
        got_twin = getattr(kernels_numpy, name)(*twin)
        if name in {"normals_and_box", "polarity", "acquire_mask"}:
            np.testing.assert_allclose(got_twin, got_fast, rtol=RTOL)
        if name == "fit_passes":  # the scratch arrays hold both kernels' temporaries
            state = fast[FIT_STATE]
            kept = int(state[ST_KEPT])
            lost += int(fast[FIT_OUT][kept][OUT_STATUS] != 0)
            resumed += int(state[ST_NEED_WINDOW] != 0)
            for row in PRIVATE_ROWS:
                fast[FIT_SCRATCH][:, row] = twin[FIT_SCRATCH][:, row] = 0.0
        for a, b in zip(twin, fast, strict=True):
            if isinstance(a, np.ndarray):
                np.testing.assert_allclose(a, b, rtol=RTOL, atol=1e-12, err_msg=name)
    assert 0 < lost < len(recorder.calls)  # both branches of the pass: found and lost
    assert resumed > 0  # both return for a window the caller computes, then resume


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


def test_the_sobel_pair_gives_opencvs_values_bit_for_bit() -> None:
    """The gradient's one-pass Sobel (both implementations) against two cv2.Sobel calls, on
    smoothed windows of every shape class: 1-3 px (the reflected border folds on itself) up to
    a target's window."""
    rng = np.random.default_rng(5)
    shapes = [(h, w) for h in (1, 2, 3) for w in (1, 2, 3)] + [(5, 160), (97, 64), (131, 152)]
    for h, w in shapes:
        noise = (rng.random((h, w)) * 255).astype(np.uint8).astype(np.float32)
        b = np.asarray(cv2.GaussianBlur(noise, (0, 0), 1.0), dtype=np.float32)
        want_x = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        want_y = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        for impl in (kernels, kernels_numpy):
            gx, gy = np.full_like(b, np.nan), np.full_like(b, np.nan)
            impl.sobel_pair(b, gx, gy)
            assert np.array_equal(gx, want_x), (impl.__name__, h, w)
            assert np.array_equal(gy, want_y), (impl.__name__, h, w)


def test_the_slow_error_autocovariances_are_the_twins_bit_for_bit() -> None:
    """slow_error_gammas (SlowErrors' sums) gives its twin's Python sums bit for bit, from the
    first window it runs on (12 bursts, 3 lags) to a full one (60, 10)."""
    rng = np.random.default_rng(9)
    for n, lags in ((12, 3), (31, 9), (60, 10)):
        x = np.log(0.04) + np.cumsum(rng.normal(0.0, 0.003, n))
        s = rng.uniform(0.002, 0.02, n)
        fast, twin = np.full(lags + 1, np.nan), np.full(lags + 1, np.nan)
        kernels.slow_error_gammas(x, s, lags, fast)
        kernels_numpy.slow_error_gammas(x, s, lags, twin)
        assert np.array_equal(fast, twin), n
        assert fast[0] > 0


def test_the_world_point_and_its_covariance_are_the_twins_bit_for_bit() -> None:
    """cartesian_point (a centroid at pan/tilt and depth as a world point, with its
    covariance) gives its twin's float operations bit for bit, over the head's range."""
    rng = np.random.default_rng(4)
    for _ in range(200):
        u, v = rng.uniform(0.0, 640.0), rng.uniform(0.0, 480.0)
        pan, tilt = rng.uniform(-100.0, 100.0), rng.uniform(-25.0, 25.0)
        z = rng.uniform(0.5, 30.0)
        args = (u, v, pan, tilt, z, 0.02 * z, 0.3, 0.02, 0.0074, 35.0, 319.5, 239.5)
        fast_w, fast_c = np.full(3, np.nan), np.full((3, 3), np.nan)
        twin_w, twin_c = np.full(3, np.nan), np.full((3, 3), np.nan)
        kernels.cartesian_point(*args, fast_w, fast_c)
        kernels_numpy.cartesian_point(*args, twin_w, twin_c)
        assert np.array_equal(fast_w, twin_w), args
        assert np.array_equal(fast_c, twin_c), args
        assert np.array_equal(fast_c, fast_c.T)


def test_the_acquisition_mask_gives_opencvs_threshold_and_mask_bit_for_bit() -> None:
    """acquire_mask (both implementations) against OpenCV's resize, 5×5 blur and Otsu threshold
    on frames of a disc, noise and flat regions, whole (halved) and as regions (as is), of
    3×3 up to a whole frame."""
    rng = np.random.default_rng(8)
    frames = [render_disc(W, H, (320.5, 240.2), 60.0, 2.0, rng=rng)]
    frames.append((rng.random((H, W)) * 255).astype(np.uint8))
    frames.append(np.full((H, W), 77, dtype=np.uint8))  # one level: Otsu's threshold is 0
    cases = [(0, 0, W // 2, H // 2, 2), (31, 17, 101, 57, 2), (5, 9, 3, 3, 1)]
    cases += [(int(rng.integers(0, 300)), int(rng.integers(0, 200)), 150, 93, 1)]
    for gray in frames:
        for x, y, w, h, scale in cases:
            region = gray[y : y + h * scale, x : x + w * scale]
            if scale > 1:
                region = cv2.resize(region, (w, h), interpolation=cv2.INTER_AREA)
            blurred = cv2.GaussianBlur(region, (5, 5), 1.0)
            want_t, want = cv2.threshold(blurred, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
            for impl in (kernels, kernels_numpy):
                out = np.full((h, w), 7, dtype=np.uint8)
                got_t = impl.acquire_mask(gray, x, y, scale, out)
                assert got_t == want_t, (impl.__name__, x, y, w, h, scale)
                assert np.array_equal(out, want), (impl.__name__, x, y, w, h, scale)


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
    """A moving, growing disc with blurred frames, clutter across its edge, a jolted frame and one
    lost frame."""
    rng = np.random.default_rng(21)
    tracker = ContourTracker(TrackerConfig(relax=0.2))
    img = render_disc(W, H, (300.3, 230.7), 40.0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    out = []
    for k in range(1, 30):
        # frame 15 is jolted 8 px: passes that leave the first window resume for another one
        c = (300.3 + 1.7 * k + (8.0 if k == 15 else 0.0), 230.7 - 0.9 * k)
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


def test_the_bilinear_samples_are_opencvs_remap() -> None:
    """Both kernels sample the gradient window as cv2.remap(INTER_LINEAR) did before them:
    inside, across and beyond the window's border."""
    rng = np.random.default_rng(5)
    g = (rng.standard_normal((2, 60, 70)) * 40).astype(np.float32)
    n, s = 64, 12
    pts = np.column_stack([rng.uniform(-8, 78, n), rng.uniform(-8, 68, n)])
    angle = rng.uniform(0, 2 * np.pi, n)
    normals = np.column_stack([np.cos(angle), np.sin(angle)])
    x0, y0 = 3.0, 2.0  # the window's corner in the frame
    steps = np.arange(-s, s + 1)[None, :]
    mapx = (pts[:, 0:1] + steps * normals[:, 0:1] - x0).astype(np.float32)
    mapy = (pts[:, 1:2] + steps * normals[:, 1:2] - y0).astype(np.float32)
    expected = [cv2.remap(g[c], mapx, mapy, cv2.INTER_LINEAR) for c in (0, 1)]
    for impl in (kernels, kernels_numpy):
        bx = np.empty((n, 2 * s + 1), dtype=np.float32)
        by = np.empty_like(bx)
        impl.sample_normals(g[0], g[1], x0, y0, pts, normals, s, bx, by)
        # float32 rounding: OpenCV's SIMD path fuses the multiply-adds where the CPU has FMA
        np.testing.assert_allclose(bx, expected[0], rtol=1e-6, atol=1e-4)
        np.testing.assert_allclose(by, expected[1], rtol=1e-6, atol=1e-4)
