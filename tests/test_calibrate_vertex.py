"""The closed loop's reading of a sweep (dffd.calibrate_vertex) on synthetic cost curves."""

from __future__ import annotations

import numpy as np
import pytest

from dffd.calibrate_parabola import fit_vertex
from dffd.calibrate_vertex import closed_loop_vertex

H = 1.0  # the half-bracket (the sweep's unit)
NOISE = 0.002  # relative noise of a setting's mean cost


def _skewed(x: np.ndarray, skew: float) -> np.ndarray:
    """A cost with its minimum at 0 that rises faster on one side: not even in defocus."""
    t = x / H
    return 1.0 + t * t + skew * t * t * np.tanh(2.0 * t)


def _sweep(
    skew: float, seed: int, lo: float = -2.0, hi: float = 2.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.linspace(lo, hi, 41)
    g = _skewed(x, skew) * (1.0 + NOISE * rng.standard_normal(len(x)))
    return x, g, NOISE * g


def _three_point_vertex(c: float, skew: float) -> float:
    gm, g0, gp = (float(_skewed(np.array([c + d]), skew)[0]) for d in (-H, 0.0, H))
    return c + H * (gm - gp) / (2.0 * (gm - 2.0 * g0 + gp))


@pytest.mark.parametrize("seed", range(4))
def test_the_reading_is_where_the_brackets_ends_cost_the_same(seed: int) -> None:
    """On a skewed cost the least-squares vertex of the ± h window and the closed loop's fixed
    point differ; the reading is the fixed point: g(x − h) = g(x + h), within the noise."""
    x, g, s = _sweep(0.6, seed)
    ls = fit_vertex(x, g, s, H)
    assert ls is not None
    found = closed_loop_vertex(x, g, s, H, start=ls.x)
    assert found is not None
    assert not found.pinned
    # the noiseless curve's two ends at the reading cost the same (to a few noise σ)
    gm, gp = _skewed(np.array([found.x - H, found.x + H]), 0.6)
    assert abs(gm - gp) / gm < 3 * NOISE
    # the true fixed point, by bisection on the noiseless curve
    a, b = -0.5, 0.5
    for _ in range(60):
        m = 0.5 * (a + b)
        d = np.diff(_skewed(np.array([m + H, m - H]), 0.6))[0]
        a, b = (m, b) if d > 0 else (a, m)
    truth = 0.5 * (a + b)
    assert abs(found.x - truth) < 4 * found.sigma + 0.005
    assert abs(ls.x - truth) > 0.03  # the estimators differ here: the test means something
    assert found.sigma < 0.05


def test_an_even_cost_reads_its_minimum() -> None:
    """For a cost even in defocus the reading is the sharpest setting (both estimators agree)."""
    x, g, s = _sweep(0.0, 7)
    found = closed_loop_vertex(x, g, s, H, start=0.1)
    assert found is not None
    assert abs(found.x) < 0.02


def test_a_bracket_at_the_end_of_the_focus_range_is_pinned() -> None:
    """Where c − h would pass the end of the focus range the bracket is shifted (plan_burst):
    the reading is the three-point vertex of the pinned bracket, not a fixed point."""
    x, g, s = _sweep(0.6, 3, lo=-0.5, hi=2.5)
    found = closed_loop_vertex(x, g, s, H, start=0.0, ends=(-0.5, 10.0))
    assert found is not None
    assert found.pinned
    assert found.centre == pytest.approx(0.5)
    assert found.x == pytest.approx(_three_point_vertex(0.5, 0.6), abs=0.02)


def test_a_sweep_that_does_not_reach_the_bracket_gives_none() -> None:
    """No extrapolation: the caller falls back to the least-squares vertex."""
    x, g, s = _sweep(0.0, 1, lo=-0.6, hi=2.0)
    assert closed_loop_vertex(x, g, s, H, start=0.0) is None


def test_the_response_is_the_three_point_vertex_around_the_fixed_point() -> None:
    """``offsets_h``: on the same smoothed sweep, the vertex the estimator fits with its bracket
    δ h off the fixed point — 0 at δ = 0, the noiseless curve's three-point vertex elsewhere
    (here S-shaped: the skewed cost is not a parabola); NaN where the bracket leaves the sweep."""
    x, g, s = _sweep(0.6, 1)
    offsets = (-0.9, -0.5, 0.0, 0.5, 1.5)
    found = closed_loop_vertex(x, g, s, H, start=0.0, offsets_h=offsets)
    assert found is not None
    assert len(found.response_h) == len(offsets)
    assert found.response_h[2] == pytest.approx(0.0, abs=1e-6)
    for d, r in zip(offsets[:-1], found.response_h[:-1], strict=True):
        c = found.x - d * H
        assert r == pytest.approx((_three_point_vertex(c, 0.6) - c) / H, abs=0.02)
    assert np.isnan(found.response_h[-1])  # the bracket ± h around x − 1.5 h leaves ± 2 h
    assert closed_loop_vertex(x, g, s, H, start=0.0).response_h == ()  # type: ignore[union-attr]
