"""VelocityEstimator: the three axes in one step are three Differentiators, value for value."""

from __future__ import annotations

import math

import numpy as np

from dffd.core.filters import Differentiator
from dffd.core.geometry import VelocityEstimator


def _reference(omega: float, steps: list[tuple[tuple[float, float, float], float]]) -> list:
    axes = [Differentiator(omega) for _ in range(3)]
    return [tuple(ax.update(c, dt)[1] for ax, c in zip(axes, p, strict=True)) for p, dt in steps]


def test_velocity_estimator_equals_three_differentiators_exactly() -> None:
    rng = np.random.default_rng(7)
    steps: list[tuple[tuple[float, float, float], float]] = []
    for k in range(200):
        t = k / 30.0
        p = (0.3 * math.sin(t), 0.1 * t + 1e-3 * rng.normal(), 2.0 + 0.5 * math.cos(0.7 * t))
        dt = 0.0 if k % 37 == 5 else float(rng.uniform(0.02, 0.07))  # a repeated time too
        steps.append((p, dt))
    for omega in (4.0, 40.0 / 3.0):
        est = VelocityEstimator(omega)
        got = [est.update(p, dt) for p, dt in steps]
        assert got == _reference(omega, steps)  # bit for bit, not to a tolerance
        assert got[0] == (0.0, 0.0, 0.0)  # the first sample starts at rest
        est.reset()
        assert [est.update(p, dt) for p, dt in steps[:20]] == _reference(omega, steps[:20])


def test_velocity_estimator_follows_a_ramp() -> None:
    est = VelocityEstimator(10.0)
    v = (0.0, 0.0, 0.0)
    for k in range(300):
        t = k / 30.0
        v = est.update((0.5 * t, -0.2 * t, 1.0), 1 / 30.0)
    # (held samples of a ramp: the derivative of the staircase lags by ~1 %)
    assert np.allclose(v, (0.5, -0.2, 0.0), rtol=0.02, atol=1e-9)
