"""Focus cost, burst fit and burst planning."""

from __future__ import annotations

import numpy as np
import pytest

from dffd.core.contour import ContourTracker, TrackerConfig, find_target
from dffd.core.focus import fit_burst, focus_cost, plan_burst
from dffd.core.synthetic import DiscScene, render_scene, synthetic_lens

LENS = synthetic_lens()


def _parabola(v: np.ndarray, v_true: float) -> np.ndarray:
    return 3e3 * (v - v_true) ** 2 + 0.02


def test_three_point_fit_is_exact_on_a_parabola() -> None:
    v_true = LENS.v_from_depth(4.0)
    v = np.array([v_true - 0.08, v_true + 0.01, v_true + 0.1])
    fit = fit_burst(v, _parabola(v, v_true), np.full(3, 1e-4), LENS)
    assert fit.accepted
    assert fit.reason == "ok"
    assert fit.v_hat_mm == pytest.approx(v_true, abs=1e-9)
    assert fit.z_m == pytest.approx(4.0, rel=1e-6)
    assert fit.alpha == pytest.approx(3e3, rel=1e-6)
    assert fit.sigma_m is not None
    assert fit.sigma_m > 0


def test_weighted_least_squares_with_more_points_and_poor_residual() -> None:
    v_true = LENS.v_from_depth(6.0)
    v = v_true + np.linspace(-0.1, 0.1, 5)
    rng = np.random.default_rng(1)
    g = _parabola(v, v_true) * (1 + 0.002 * rng.standard_normal(5))
    fit = fit_burst(v, g, 0.002 * g, LENS)
    assert fit.accepted
    assert fit.z_m == pytest.approx(6.0, rel=0.02)
    bad = g.copy()
    bad[1] *= 1.5
    rejected = fit_burst(v, bad, 0.002 * g, LENS)
    assert not rejected.accepted
    assert rejected.reason == "poor residual"


@pytest.mark.parametrize(
    ("g", "reason"),
    [
        ([1.0, 0.5, 1.0], "ok"),
        ([0.5, 1.0, 0.5], "alpha <= 0"),
        ([1.0, 0.35, 0.1], "outside the bracket"),
        ([1.0, 0.5, 0.0001], "far outside"),
    ],
)
def test_acceptance_checks_give_reasons(g: list[float], reason: str) -> None:
    v_mid = LENS.v_from_depth(4.0)
    v = [v_mid - 0.05, v_mid, v_mid + 0.05]
    fit = fit_burst(v, g, [1e-4] * 3, LENS)
    assert reason in fit.reason
    assert fit.accepted == (reason in ("ok", "outside the bracket"))


def test_too_few_settings_rejected() -> None:
    fit = fit_burst([31.1, 31.1, 31.2], [1.0, 1.0, 2.0], [0.01] * 3, LENS)
    assert not fit.accepted
    assert "three distinct" in fit.reason


def test_plan_spacing_depends_on_depth_and_order_minimises_travel() -> None:
    near = plan_burst(LENS, 4096, 2.0, 0.001)
    far = plan_burst(LENS, 4096, 8.0, 0.001)
    for plan, z in ((near, 2.0), (far, 8.0)):
        v = [LENS.v_from_counts(c) for c in plan]
        v_sharp = LENS.v_from_depth(z)
        assert min(v) < v_sharp < max(v)
        # outer settings blur by ~3 px (constant blur circle)
        blur = [LENS.blur_radius_px(x, v_sharp, 2.9) for x in (min(v), max(v))]
        assert blur == pytest.approx([3.0, 3.0], abs=0.3)
        assert abs(plan[0] - 4096) < abs(plan[2] - 4096)  # nearest end first
    # counts spacing differs with depth (the table is nonlinear): depth-dependent spacing
    assert (near[2] - near[0]) != (far[2] - far[0])
    rev = plan_burst(LENS, 40000, 8.0, 0.001)
    assert rev == tuple(reversed(far))
    # a large uncertainty widens the bracket, the missing prediction spans the working range
    wide = plan_burst(LENS, 4096, 3.0, 1.0)
    narrow = plan_burst(LENS, 4096, 3.0, 0.001)
    assert wide[2] - wide[0] > narrow[2] - narrow[0]
    init = plan_burst(LENS, 4096, None, None)
    assert LENS.v_from_counts(init[0]) <= LENS.v_from_depth(12.0) + 1e-4  # count rounding
    assert LENS.v_from_counts(init[2]) >= LENS.v_from_depth(1.5) - 1e-4


def test_cost_on_rendered_images_gives_the_depth() -> None:
    scene = DiscScene()
    rng = np.random.default_rng(5)
    z = 5.0
    c0 = LENS.counts_for_depth(z)
    img = render_scene(scene, LENS, c0, (0.02, 0.0, z), rng)
    poly = find_target(img)
    assert poly is not None
    tracker = ContourTracker(TrackerConfig())
    assert tracker.start(img, poly, 0.0)
    v, g, s = [], [], []
    for c in plan_burst(LENS, c0, z * 1.01, 0.05):
        obs = tracker.update(render_scene(scene, LENS, c, (0.02, 0.0, z), rng), 0.0, "similarity")
        cost = focus_cost(obs.peak_sq)
        assert cost is not None
        v.append(LENS.v_from_counts(c))
        g.append(cost[0])
        s.append(cost[1])
    assert g[1] < min(g[0], g[2])
    fit = fit_burst(v, g, s, LENS)
    assert fit.accepted
    assert fit.z_m == pytest.approx(z, abs=0.05)


def test_focus_cost_needs_enough_normals() -> None:
    assert focus_cost(np.full(5, 4.0)) is None
    g = focus_cost(np.full(64, 4.0))
    assert g is not None
    assert g[0] == pytest.approx(0.25)
