"""The focus bench's closed-loop fixed point (hil/bench_focus.py)."""

from __future__ import annotations

import math

import numpy as np

from hil.bench_focus import fixed_point


def test_fixed_point_is_where_the_mean_fitted_offset_crosses_zero() -> None:
    delta = np.repeat([-0.2, -0.1, 0.0, 0.1], 3)
    x_hat = 1.15 * delta + 0.08 + np.tile([-0.001, 0.0, 0.001], 4)  # the aberrated lens's lean
    assert math.isclose(fixed_point(delta, x_hat), -0.08 / 1.15, abs_tol=1e-9)


def test_fixed_point_without_a_crossing_is_nan() -> None:
    delta = np.array([0.0, 0.1, 0.2])
    assert math.isnan(fixed_point(delta, delta + 1.0))
