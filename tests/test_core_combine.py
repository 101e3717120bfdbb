"""The debiased_peak focus measure: the peak gradient's bias fitted against the edge moment."""

from __future__ import annotations

import numpy as np
import pytest

from dffd.core.combine import CombineConfig, PeakBias, combine_vertices


def test_peak_bias_recovers_offset_and_slope() -> None:
    rng = np.random.default_rng(2)
    bias = PeakBias(CombineConfig(window_bursts=1e9, prior_slope=0.1))
    for _ in range(400):
        x = rng.uniform(-0.5, 0.5)
        bias.update(x, 0.05 - 0.07 * x + rng.normal(0.0, 0.005), 0.005**2)
    b0, b1 = bias.theta
    assert b0 == pytest.approx(0.05, abs=0.002)
    assert b1 == pytest.approx(-0.07, abs=0.01)
    mean, var = bias.correction(0.3)
    assert mean == pytest.approx(0.05 - 0.021, abs=0.003)
    assert 0.0 < var < 0.002**2
    assert bias.residual_var == pytest.approx(0.005**2, rel=0.2)


def test_default_fit_is_the_offset_alone() -> None:
    # b1 held at 0: the slope term would carry the edge moment's per-burst noise (§13)
    rng = np.random.default_rng(4)
    bias = PeakBias()
    for _ in range(300):
        x = rng.normal(0.0, 0.03)
        bias.update(x, 0.07 + 0.14 * x + rng.normal(0.0, 0.004), 0.004**2)
    b0, b1 = bias.theta
    assert b1 == 0.0
    assert b0 == pytest.approx(0.07, abs=0.002)


def test_first_burst_uses_the_edge_moment_alone() -> None:
    bias = PeakBias()
    x, var = combine_vertices(0.1, 0.01**2, 0.2, 0.005**2, bias)
    assert (x, var) == (0.1, 0.01**2)  # no bias known yet: the edge moment's vertex
    assert bias.count == 1


def test_debiased_vertex_has_the_edge_moments_bias_and_the_peaks_noise() -> None:
    """A stream of bursts in closed loop (offsets spread 0.03 h): the peak gradient is precise
    but leans +0.07 h (the aberrated lens's fixed point), the edge moment is unbiased and 2×
    noisier; the debiased peak is unbiased with the peak gradient's noise."""
    rng = np.random.default_rng(5)
    bias = PeakBias()
    s_ev, s_pg = 0.006, 0.003
    err_c, err_ev = [], []
    for k in range(600):
        x = rng.normal(0.0, 0.03)
        x_ev = x + rng.normal(0.0, s_ev)
        x_pg = 0.07 + x + rng.normal(0.0, s_pg)
        xc, var = combine_vertices(x_ev, s_ev**2, x_pg, s_pg**2, bias)
        if k >= 50:  # the bias fit has converged: the peak gradient's variance plus the fit's
            assert s_pg**2 < var < 0.5 * s_ev**2
        if k >= 100:
            err_c.append(xc - x)
            err_ev.append(x_ev - x)
    assert abs(float(np.mean(err_c))) < 0.001
    assert float(np.std(err_c)) < 0.75 * float(np.std(err_ev))
