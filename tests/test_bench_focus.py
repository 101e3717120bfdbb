"""The focus bench's closed-loop fixed point (hil/bench_focus.py)."""

from __future__ import annotations

import math

import numpy as np

from hil.bench_focus import MEASURES, fixed_point, measure


def test_fixed_point_is_where_the_mean_fitted_offset_crosses_zero() -> None:
    delta = np.repeat([-0.2, -0.1, 0.0, 0.1], 3)
    x_hat = 1.15 * delta + 0.08 + np.tile([-0.001, 0.0, 0.001], 4)  # the aberrated lens's lean
    assert math.isclose(fixed_point(delta, x_hat), -0.08 / 1.15, abs_tol=1e-9)


def test_fixed_point_without_a_crossing_is_nan() -> None:
    delta = np.array([0.0, 0.1, 0.2])
    assert math.isnan(fixed_point(delta, delta + 1.0))


def test_the_bench_reports_the_calibrated_measure_corrected_by_its_response() -> None:
    """``measure(..., response=)`` adds ``<measure>+response``: on a disc PSF its slope across
    the bracket is 1 where the raw peak gradient's is ~0.92 (the synthetic disc of
    tests/test_core_focus.py, its response measured on that disc's sweeps)."""
    from dffd.core.synthetic import render_disc, synthetic_lens
    from tests.test_core_focus import _response

    rng = np.random.default_rng(4)

    def render(v0: float, repeat: int) -> np.ndarray:
        return render_disc(
            200, 200, (100.3, 99.6), 40.0, 3.0 * (v0 - 32.0) / 0.1, rng=rng, sampled=True
        )

    out = measure(
        render, 32.0, 0.1, synthetic_lens(), deltas=[-0.9, -0.45, 0.0, 0.45, 0.9], repeats=1,
        response=_response("disc"),
    )  # fmt: skip
    assert set(out) == {*MEASURES, "peak_gradient+response"}
    assert math.isclose(out["peak_gradient+response"]["slope"], 1.0, abs_tol=0.03)
    assert out["peak_gradient"]["slope"] < 0.95
