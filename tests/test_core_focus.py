"""Focus cost, burst fit and burst planning."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest

from dffd.calibrate_vertex import table_response
from dffd.core.acquisition import find_target
from dffd.core.contour import ContourTracker, TrackerConfig
from dffd.core.focus import (
    FitConfig,
    edge_variance_cost,
    fit_burst,
    focus_cost,
    frame_cost,
    plan_burst,
)
from dffd.core.lens import Lens, VertexResponse
from dffd.core.synthetic import DiscScene, render_disc, render_scene, synthetic_lens

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


# -- focus measure: the vertex follows the true offset for any PSF shape ---------------------
def _vertex_offset(psf: str, delta: float, measure: str, rng: np.random.Generator) -> float:
    """Three-setting burst with outer blur 3 px, sharp setting at δ (bracket units); vertex."""
    tracker = ContourTracker(TrackerConfig())
    g, s = [], []
    for x in (-1.0, 0.0, 1.0):
        img = render_disc(
            200, 200, (100.3, 99.6), 40.0, 3.0 * (x - delta), psf=psf, rng=rng, sampled=True
        )  # type: ignore[arg-type]
        poly = find_target(img)
        assert poly is not None
        assert tracker.start(img, poly, 0.0)
        cost = frame_cost(tracker.update(img, 0.0, "similarity"), measure)  # type: ignore[arg-type]
        assert cost is not None
        g.append(cost[0])
        s.append(cost[1])
    fit = fit_burst([31.9, 32.0, 32.1], g, s, LENS)
    assert fit.accepted, fit.reason
    return (fit.v_hat_mm - 32.0) / 0.1


@pytest.mark.parametrize("psf", ["gaussian", "disc", "aberrated"])
def test_edge_variance_vertex_has_unit_slope_for_any_psf(psf: str) -> None:
    rng = np.random.default_rng(3)
    deltas = np.array([-0.6, -0.3, 0.0, 0.3, 0.6])
    fitted = np.array([_vertex_offset(psf, d, "edge_variance", rng) for d in deltas])
    slope, intercept = np.polyfit(deltas, fitted, 1)
    # measured: 0.997 / 0.999 / 0.995, |intercept| ≤ 0.006 (3 repeats, /tmp/synth_slope.py)
    assert slope == pytest.approx(1.0, abs=0.03)
    assert abs(intercept) < 0.02
    assert np.max(np.abs(fitted - deltas)) < 0.03


def test_peak_gradient_vertex_is_biased_by_an_aberrated_psf() -> None:
    # why the default measure changed: the old cost's vertex leans with the PSF's asymmetry
    rng = np.random.default_rng(3)
    deltas = np.array([-0.6, 0.0, 0.6])
    old = np.array([_vertex_offset("aberrated", d, "peak_gradient", rng) for d in deltas])
    new = np.array([_vertex_offset("aberrated", d, "edge_variance", rng) for d in deltas])
    assert np.max(np.abs(old - deltas)) > 2.5 * np.max(np.abs(new - deltas))


def _closed_loop_lean(psf: str, measure: str, repeats: int) -> float:
    """Mean fitted offset at the true sharp setting (h): where a closed loop that re-centres
    each bracket on its vertex settles, less the truth (slope ~1 here, so about −δ*)."""
    rng = np.random.default_rng(11)
    return float(np.mean([_vertex_offset(psf, 0.0, measure, rng) for _ in range(repeats)]))


def test_debiasing_moment_has_no_lean_on_an_aberrated_psf() -> None:
    # The lean an aberrated PSF adds over a Gaussian one (the same noise draws: the difference
    # is the PSF's). The edge moment on 3 spreads cuts more of the halo side's tail (+0.0069 h;
    # the peak gradient: +0.081 h); the debiasing moment's 3.5 spreads do not (+0.0009 h).
    def extra_lean(measure: str) -> float:
        return _closed_loop_lean("aberrated", measure, 8) - _closed_loop_lean(
            "gaussian", measure, 8
        )

    assert extra_lean("edge_variance") > 0.004
    assert abs(extra_lean("debiased_peak")) < 0.0015


def test_edge_variance_grows_as_the_blur_variance_on_both_sides_of_focus() -> None:
    blurs = np.array([-4.0, -2.0, 0.0, 2.0, 4.0])
    for psf in ("gaussian", "disc", "aberrated"):
        values = []
        for b in blurs:
            img = render_disc(
                200, 200, (100.3, 99.6), 40.0, b, psf=psf, noise_std=0.0, sampled=True
            )  # type: ignore[arg-type]
            poly = find_target(img)
            assert poly is not None
            tracker = ContourTracker(TrackerConfig())
            assert tracker.start(img, poly, 0.0)
            cost = frame_cost(tracker.update(img, 0.0, "similarity"), "edge_variance")
            assert cost is not None
            values.append(cost[0])
        curvature, linear, _ = np.polyfit(blurs, values, 2)
        # every PSF here has the per-axis variance b²/4 + const: the measure adds it exactly
        assert curvature == pytest.approx(0.25, rel=0.03), psf
        assert abs(linear) < 0.01, psf


def test_edge_variance_cost_pools_normals_by_mass_and_needs_enough_of_them() -> None:
    assert edge_variance_cost(np.full(5, 2.0), np.ones(5)) is None
    assert edge_variance_cost(None, None) is None
    var = np.full(64, 2.0)
    var[:3] = np.nan
    var[10] = 50.0  # an occluded normal: trimmed
    cost = edge_variance_cost(var, np.full(64, 100.0))
    assert cost is not None
    assert cost[0] == pytest.approx(2.0)


def test_the_trackers_pooled_cost_equals_the_reference_pooling() -> None:
    rng = np.random.default_rng(11)
    img = render_disc(200, 200, (100.3, 99.6), 30.0, 2.5, psf="aberrated", rng=rng)
    poly = find_target(img)
    assert poly is not None
    tracker = ContourTracker(TrackerConfig())
    assert tracker.start(img, poly, 0.0)
    obs = tracker.update(img, 0.0, "similarity")
    pooled = frame_cost(obs, "edge_variance")
    moments = obs.edge_moments()
    assert moments is not None
    reference = edge_variance_cost(moments.var, moments.mass, TrackerConfig().trim_fraction)
    assert pooled is not None
    assert reference is not None
    assert pooled == pytest.approx(reference, rel=1e-9)
    assert frame_cost(obs, "peak_gradient") == focus_cost(obs.peak_sq)


def test_compiled_focus_cost_is_the_numpy_twins_bit_for_bit() -> None:
    # The compiled cost reproduces NumPy's pairwise sums (blocks of 8 running sums, halving
    # above 128 values): the same g and σ_g to the last bit, NaN normals and short lists too.
    from dffd.core import kernels_stats, kernels_stats_numpy

    rng = np.random.default_rng(11)
    for n in [*range(1, 40), 63, 64, 65, 127, 128, 129, 200, 257, 300, 1031]:
        for _ in range(3):
            peaks = rng.lognormal(2.0, 1.5, n)
            peaks[rng.random(n) < 0.1] = np.nan
            for trim in (0.0, 0.1, 0.25):
                got, want = np.full(2, -1.0), np.full(2, -1.0)
                ok = kernels_stats.focus_cost(peaks, trim, got)
                assert ok == kernels_stats_numpy.focus_cost(peaks, trim, want)
                assert got.tolist() == want.tolist()


# -- the calibration's vertex response corrects the peak gradient's vertex for any PSF --------
SWEEP_X = np.round(np.arange(-2.2, 2.21, 0.1), 2)  # settings of a sweep, in half-brackets


def _cost(psf: str, blur_px: float, rng: np.random.Generator) -> tuple[float, float]:
    img = render_disc(200, 200, (100.3, 99.6), 40.0, blur_px, psf=psf, rng=rng, sampled=True)  # type: ignore[arg-type]
    poly = find_target(img)
    assert poly is not None
    tracker = ContourTracker(TrackerConfig())
    assert tracker.start(img, poly, 0.0)
    cost = frame_cost(tracker.update(img, 0.0, "similarity"), "peak_gradient")
    assert cost is not None
    return cost


@functools.cache
def _response(psf: str) -> VertexResponse:
    """The response ``dffd calibrate`` measures on three sweeps of the synthetic disc (the
    bracket of _vertex_offset: ± 0.1 mm of v at 32 mm, 3 px of outer blur)."""
    lens = Lens("sweep", 30.0, 0.005, (0, 100_000), (31.0, 33.0), f_number=2.0)
    per_px = lens.pixel_pitch_mm * 2.0 * 2.0 / lens.focal_length_mm
    rng = np.random.default_rng(5)
    sweeps = []
    for _ in range(3):
        costs = [_cost(psf, 3.0 * x, rng) for x in SWEEP_X]
        counts = (32.0 + 0.1 * SWEEP_X - 31.0) * 50_000.0
        sweeps.append((4.0, [(c, g, s) for c, (g, s) in zip(counts, costs, strict=True)]))
    response, lines = table_response(lens, sweeps, "peak_gradient", 0.1 / 32.0 / per_px, 2.8)
    assert response is not None, lines
    # 0 at the fixed point: the correction must not move where the closed loop settles (the
    # table's point); a response read on another smoothing than the fixed point's was +0.001 h
    # off there, a bias ∝ z² in closed loop
    assert abs(response.correct(0.0)[0]) < 1e-5
    return response


def _offsets(
    psf: str, deltas: np.ndarray, response: VertexResponse | None, repeats: int = 1
) -> np.ndarray:
    """Fitted offsets (h) of bursts with the sharp setting δ h off the bracket centre."""
    rng = np.random.default_rng(3)
    out = np.empty((repeats, len(deltas)))
    for r in range(repeats):
        for i, d in enumerate(deltas):
            costs = [_cost(psf, 3.0 * (x - d), rng) for x in (-1.0, 0.0, 1.0)]
            fit = fit_burst(
                [31.9, 32.0, 32.1], [c[0] for c in costs], [c[1] for c in costs], LENS,
                response=response,
            )  # fmt: skip
            assert fit.accepted, fit.reason
            out[r, i] = (fit.v_hat_mm - 32.0) / 0.1
    return out


@pytest.mark.parametrize("psf", ["gaussian", "disc", "aberrated"])
def test_the_vertex_response_gives_unit_slope_across_the_bracket(psf: str) -> None:
    """The peak gradient's three-point vertex is an S-shaped function of the true offset for a
    disc or an aberrated PSF (slope ~0.93 over ± 0.9 h, > 1.05 near the centre); corrected by
    the response measured on the sweeps it has slope 1 across the bracket (the aberrated PSF's
    lean stays: the table absorbs it)."""
    response = _response(psf)
    deltas = np.array([-0.9, -0.6, -0.3, -0.1, 0.0, 0.1, 0.3, 0.6, 0.9])
    near = np.abs(deltas) <= 0.3
    raw = _offsets(psf, deltas, None)[0]
    fixed = _offsets(psf, deltas, response)[0]
    slope, _ = np.polyfit(deltas, fixed, 1)
    local, _ = np.polyfit(deltas[near], fixed[near], 1)
    raw_slope, _ = np.polyfit(deltas, raw, 1)
    raw_local, _ = np.polyfit(deltas[near], raw[near], 1)
    assert slope == pytest.approx(1.0, abs=0.03)
    assert local == pytest.approx(1.0, abs=0.03)
    if psf != "gaussian":  # the correction is what makes it so
        assert max(abs(raw_slope - 1.0), abs(raw_local - 1.0)) > 0.05


def test_the_response_adds_no_noise_on_a_gaussian_psf() -> None:
    """On a Gaussian PSF the cost is a parabola: the measured response is the identity within a
    few %, so the corrected vertex is no noisier (its gain d true/d fitted ≤ 1.04 across the
    bracket); on the disc it is < 1 near the centre (the raw vertex overshoots there)."""
    gains = [_response("gaussian").correct(x)[1] for x in np.linspace(-0.9, 0.9, 19)]
    assert max(gains) < 1.04
    assert min(gains) > 0.96
    assert _response("disc").correct(0.0)[1] < 0.95


def test_the_response_corrects_the_vertex_only_on_its_own_bracket_and_keeps_its_sigma() -> None:
    response = VertexResponse(
        "peak_gradient", 0.1 / 32.0, (-1.0, -0.5, 0.0, 0.5, 1.0), (-0.9, -0.55, 0.0, 0.55, 0.9)
    )
    g = _parabola(np.array([31.9, 32.0, 32.1]), 32.03)
    s = [1e-4] * 3
    raw = fit_burst([31.9, 32.0, 32.1], g, s, LENS)
    fixed = fit_burst([31.9, 32.0, 32.1], g, s, LENS, response=response)
    x, slope = response.correct((raw.v_hat_mm - 32.0) / 0.1)
    assert fixed.v_hat_mm == pytest.approx(32.0 + 0.1 * x)
    assert slope < 0.9  # near the centre the inverse response's slope would narrow σ …
    assert fixed.sigma_v_mm == pytest.approx(raw.sigma_v_mm)  # … the fitted σ is kept
    assert fixed.z_m == pytest.approx(LENS.depth_from_v(fixed.v_hat_mm))
    # a bracket twice as wide (the start-up's) is not corrected
    wide = fit_burst([31.8, 32.0, 32.2], _parabola(np.array([31.8, 32.0, 32.2]), 32.03), s,
                     LENS, response=response)  # fmt: skip
    assert wide.v_hat_mm == pytest.approx(32.03)
    # beyond the measured range the end segment's chord continues
    assert response.correct(1.08) == pytest.approx((1.0 + 0.18 / 0.35 * 0.5, 0.5 / 0.35))


@pytest.mark.parametrize(
    ("measure", "enabled", "applied"),
    [
        ("peak_gradient", True, True),
        ("peak_gradient", False, False),  # [estimators] vertex_response = false
        ("edge_variance", True, False),  # measured for another measure
        ("debiased_peak", True, False),  # two measures' vertices combined: not corrected
    ],
)
def test_the_burst_assembler_corrects_with_the_lens_files_response(
    measure: str, enabled: bool, applied: bool
) -> None:
    from dffd.core.bursts import BurstAssembler, FocusSettings

    response = VertexResponse("peak_gradient", 3e-3, (-1.0, 0.0, 1.0), (-0.9, 0.0, 0.9))
    lens = replace(LENS, vertex_response=response)
    bursts = BurstAssembler(
        FocusSettings(lens), fit=FitConfig(), focus_measure=measure, trim_fraction=0.1,
        burst_size=3, rolling_max_span_s=1.0, vertex_response=enabled,
    )  # type: ignore[arg-type]  # fmt: skip
    assert (bursts.response is response) is applied
    assert BurstAssembler(
        FocusSettings(LENS), fit=FitConfig(), focus_measure="peak_gradient", trim_fraction=0.1,
        burst_size=3, rolling_max_span_s=1.0, vertex_response=True,
    ).response is None  # a lens file without a response  # fmt: skip
