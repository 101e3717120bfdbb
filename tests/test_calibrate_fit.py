"""The fits of dffd calibrate on synthetic sweeps of a known lens (no rig): fast and exact."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dffd import calibrate_fit, calibrate_model
from dffd.calibrate import DEFAULT_DEPTHS_M
from dffd.calibrate_check import SWEEPS_DISAGREE_CHI2, check_table, table_sigma_per_depth
from dffd.calibrate_fit import AXIS_MISFIT_SIGMA, TableFit, fit_table
from dffd.calibrate_parabola import fit_vertex
from dffd.calibrate_types import DepthPoint
from dffd.core.focus import fit_burst, plan_burst
from dffd.core.lens import MM_PER_M, Lens
from dffd.resources import lens_table

TRUTH = Lens.from_toml(lens_table("sim-evi-d100"))
DEPTHS_M = (1.2, 1.5, 2.0, 2.5, 3.0, 3.5, 4.5, 5.5, 7.0, 8.5, 10.0, 12.0, 14.0, 17.0, 20.0)
F_NUMBER = 1.8
COST_NOISE = 0.02  # relative noise of a setting's mean cost (a few frames averaged)
WINDOW_BLUR_PX = 3.0  # the refit's window (calibrate_fit.VERTEX_WINDOW_BLUR_PX)


class _Optics:
    focal_length_mm = TRUTH.focal_length_mm
    pixel_pitch_mm = TRUTH.pixel_pitch_mm
    zoom_counts = None
    focus_range = (min(TRUTH.focus_counts), max(TRUTH.focus_counts))


def _half_window_mm(v_mm: float) -> float:
    return WINDOW_BLUR_PX * _Optics.pixel_pitch_mm * F_NUMBER * 2.0 / _Optics.focal_length_mm * v_mm


def _cost(v: np.ndarray, v0: float, skew: float = 0.0) -> np.ndarray:
    """Parabolic in v about ``v0`` (doubling at 3 px of blur); ``skew`` > 0: steeper on the far
    side of focus, shallower on the near one (not even in defocus)."""
    t = (v - v0) / _half_window_mm(v0)
    return np.asarray(1.0 + t * t + skew * t * t * np.tanh(2.0 * t), dtype=np.float64)


def _point(
    z_m: float,
    rng: np.random.Generator,
    off_um: float = 0.0,
    skew: float = 0.0,
    truth: Lens = TRUTH,
) -> DepthPoint:
    """A fine sweep as ``sharpest`` takes it: 41 settings over ± 7 coarse steps around the true
    focus, a cost parabolic in v (doubling at 3 px of blur; ``skew``: see _cost) with relative
    noise; its vertex in counts. ``off_um``: the sweep disturbed, its cost's minimum that far
    off in v; ``truth``: the lens swept."""
    lo, hi = _Optics.focus_range
    v0 = truth.v_from_depth(z_m)
    step = (hi - lo) / 32
    best = truth.counts_for_depth(z_m)
    counts = np.linspace(max(lo, best - 7 * step), min(hi, best + 7 * step), 41)
    v = truth.v_from_counts_array(counts)
    cost = _cost(v - off_um * 1e-3, v0, skew) * (
        1.0 + COST_NOISE * rng.standard_normal(len(counts))
    )
    sigma = COST_NOISE * cost
    found = fit_vertex(counts, cost, sigma)
    assert found is not None
    f, z = _Optics.focal_length_mm, z_m * MM_PER_M
    sweep = tuple(
        (float(c), float(g), float(s)) for c, g, s in zip(counts, cost, sigma, strict=True)
    )
    return DepthPoint(
        z_m, round(found.x), f * z / (z - f), float(cost.min()), found.x, found.sigma, sweep
    )


@pytest.mark.parametrize("noise_seed", range(8))
def test_the_table_is_not_warped_by_a_noisy_first_model(noise_seed: int) -> None:
    """Noisy sweeps of a known lens with a cost even in defocus: the table read through the
    closed loop's bracket ends is within 0.35 µm of v rms of the true one over 1.5-12 m. The
    passes map each sweep through the model's polynomial, not its spline: a spline that follows
    the readings' scatter warps the axis and feeds the scatter back (reference optics seed 1 of
    the simulator: table 2.3 -> 11.1 mm rms; the least-squares procedure before gave 0.04-0.52
    µm rms on these sweeps)."""
    rng = np.random.default_rng(noise_seed)
    table = fit_table("synthetic", _Optics(), [_point(z, rng) for z in DEPTHS_M], F_NUMBER)
    errs = [_table_err_um(table, float(z)) for z in np.geomspace(1.5, 12.0, 25)]
    assert float(np.sqrt(np.mean(np.square(errs)))) < 0.35


def test_the_closed_loop_reads_the_calibrated_depth_on_a_leaning_cost() -> None:
    """A cost that is not even in defocus (it rises faster on one side, as the aberrated optics'
    peak gradient does): the least-squares vertex and the closed loop's fixed point differ by
    several µm of v. On the table calibrated from such sweeps, the estimator's own loop
    (plan_burst + fit_burst, re-centred until it settles) reads each depth of 2-9 m within
    0.6 µm of v (0.14-0.45 µm here) — through the bracket ends, whatever the lean; on the
    least-squares procedure before, 5.0-5.8 µm."""
    rng = np.random.default_rng(11)
    skew = 0.5
    table = fit_table("leaning", _Optics(), [_point(z, rng, skew=skew) for z in DEPTHS_M], F_NUMBER)
    lens = table.lens
    for z in (2.0, 3.3, 4.8, 6.4, 9.0):
        v0 = TRUTH.v_from_depth(z)
        z_hat = z * 1.02
        for _ in range(30):
            settings = plan_burst(lens, 0, z_hat, None)
            v_true = TRUTH.v_from_counts_array(np.array(settings, dtype=np.float64))
            cost = _cost(v_true, v0, skew)
            fit = fit_burst(
                [lens.v_from_counts(c) for c in settings], list(cost), list(1e-6 * cost), lens
            )
            assert fit.accepted, fit.reason
            assert fit.z_m is not None
            z_hat = fit.z_m
        err_um = (lens.v_from_depth(z_hat) - lens.v_from_depth(z)) * 1e3
        assert abs(err_um) < 0.6, (z, err_um)
    # the same sweeps on the true table: the lean is there to absorb (a loop on the truth reads
    # the fixed point, several µm of v off)
    v0 = TRUTH.v_from_depth(6.4)
    x = np.linspace(v0 - 0.2, v0 + 0.2, 401)
    ls = fit_vertex(x, _cost(x, v0, skew), np.full(len(x), 1e-3), _half_window_mm(v0))
    assert ls is not None
    assert abs(ls.x - v0) * 1e3 > 2.0


def test_a_disturbed_sweep_is_flagged_then_outvoted_by_its_repeats() -> None:
    """One depth's sweep 1.5 µm of v off (0.25 m at 10 m): the other depths predict it badly
    and the check asks for it again; one repeat disagrees with it, so a third is asked for, and
    with three the disturbed one is dropped and the table is as good as undisturbed."""
    rng = np.random.default_rng(1)
    points = [_point(z, rng) for z in DEPTHS_M]
    clean = fit_table("clean", _Optics(), points, F_NUMBER)
    bad = DEPTHS_M.index(10.0)
    disturbed = [*points[:bad], _point(10.0, rng, off_um=1.5), *points[bad + 1 :]]
    table = fit_table("disturbed", _Optics(), disturbed, F_NUMBER)
    check = check_table(table, _Optics())
    assert check.repeat == (10.0,)
    assert abs(_table_err_um(table, 10.0)) > 0.2  # the table bent towards the bad sweep
    assert check_table(clean, _Optics()).repeat == ()  # the clean sweeps ask for nothing

    again = [*disturbed, _point(10.0, rng)]
    check = check_table(fit_table("twice", _Optics(), again, F_NUMBER), _Optics())
    twice = next(d for d in check.depths if d.z_m == 10.0)
    assert twice.n_sweeps == 2
    assert twice.sweeps_chi2 > SWEEPS_DISAGREE_CHI2
    assert check.repeat == (10.0,)  # they disagree: a third sweep decides

    thrice = fit_table("thrice", _Optics(), [*again, _point(10.0, rng)], F_NUMBER)
    check = check_table(thrice, _Optics())
    assert check.repeat == ()
    assert abs(_table_err_um(thrice, 10.0)) < 0.15
    assert abs(_table_err_um(thrice, 10.0) - _table_err_um(clean, 10.0)) < 0.15


def test_the_table_sigma_covers_its_error() -> None:
    """The table's own σ (bootstrap of the model) against its actual error over 1.5-12 m, on
    five independent synthetic calibrations: about one σ rms, never beyond four."""
    ratios = []
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        table = fit_table("s", _Optics(), [_point(z, rng) for z in DEPTHS_M], F_NUMBER)
        check = check_table(table, _Optics())
        for z in np.geomspace(1.5, 12.0, 9):
            c = TRUTH.counts_for_depth(float(z))
            err = (table.lens.v_from_counts(c) - TRUTH.v_from_counts(c)) * 1e3
            ratios.append(err / check.sigma_v_um_at(c))
    rms = float(np.sqrt(np.mean(np.square(ratios))))
    assert 0.5 < rms < 2.0, rms
    assert max(abs(r) for r in ratios) < 4.0


def test_the_table_sigma_per_depth_is_largest_where_the_others_predict_a_depth_worst() -> None:
    """The lens file's per-depth table σ (σ_v² = max(loo² − res², 0)/2 at each depth): one row
    per fitted depth at the counts it is read at, and a sweep 1.5 µm of v off at 10 m (the
    others predict it badly) gets the largest σ, several times the others' — the one number for
    the whole table would spread it over every depth."""
    rng = np.random.default_rng(1)
    points = [_point(z, rng) for z in DEPTHS_M]
    bad = DEPTHS_M.index(10.0)
    points[bad] = _point(10.0, rng, off_um=1.5)
    table = fit_table("disturbed", _Optics(), points, F_NUMBER)
    check = check_table(table, _Optics())
    rows = dict(table_sigma_per_depth(table, check))
    fitted = {round(p.at): p.z_m for p, d in zip(table.points, check.depths, strict=True)
              if math.isfinite(d.loo_v_um)}  # fmt: skip
    assert set(rows) == set(fitted)
    assert all(s >= 0 for s in rows.values())
    at_bad = next(c for c, z in fitted.items() if z == 10.0)
    others = [s for c, s in rows.items() if c != at_bad]
    assert rows[at_bad] == max(rows.values())
    assert rows[at_bad] > 3 * float(np.median(others))
    # the one number (the whole table's) sits between them
    assert float(np.median(others)) < table.lens.table_sigma_v_mm < rows[at_bad]


def _rippled(amplitude: float, cycles: int = 2) -> Lens:
    """TRUTH's focus cam with a ripple: focus power P = 1/f − 1/v plus ``amplitude`` × the
    range's power × sin(2π ``cycles`` u)/(2π ``cycles``) of the normalised counts u (the form of
    the simulator's aberrated cam, drivers/sim/optics_aberrated.py; monotone for amplitude < 1)."""
    f = TRUTH.focal_length_mm
    lo, hi = _Optics.focus_range
    counts = np.arange(lo, hi + 1, 64, dtype=np.float64)
    power = 1.0 / f - 1.0 / TRUTH.v_from_counts_array(counts)  # 1/mm
    u = (counts - lo) / (hi - lo)
    k = 2.0 * np.pi * cycles
    span = float(np.ptp(power))
    v = 1.0 / (1.0 / f - (power + amplitude * span * np.sin(k * u) / k))
    return Lens(
        "rippled", f, TRUTH.pixel_pitch_mm, tuple(int(c) for c in counts),
        tuple(float(x) for x in v),
    )  # fmt: skip


@pytest.mark.parametrize("noise_seed", range(3))
def test_the_axis_switches_to_the_whole_model_on_a_rippled_cam_only(noise_seed: int) -> None:
    """The refit passes read the sweeps through the model's polynomial unless the fit then
    misses its own bracket ends by more than AXIS_MISFIT_SIGMA of their σ (rms). On a smooth
    lens the misfit stays well below that (polynomial axis); on a cam with a ripple the
    polynomial cannot follow (the simulator's aberrated cam: 14-15 σ), the passes switch to the
    whole model — and the switched table follows the ripple better than the polynomial axis
    would have (the reason for the switch)."""
    rng = np.random.default_rng(200 + noise_seed)
    smooth = fit_table("smooth", _Optics(), [_point(z, rng) for z in DEPTHS_M], F_NUMBER)
    assert smooth.axis == "polynomial"
    assert smooth.axis_misfit_sigma < AXIS_MISFIT_SIGMA

    rippled = _rippled(0.12)
    points = [_point(z, rng, truth=rippled) for z in DEPTHS_M]
    table = fit_table("rippled", _Optics(), points, F_NUMBER)
    assert table.axis == "whole model"
    assert table.axis_misfit_sigma > 1.5 * AXIS_MISFIT_SIGMA
    assert table.fit is not None
    assert table.fit.model.spline is not None
    errs = [_table_err_um(table, float(z), rippled) for z in np.geomspace(1.5, 12.0, 25)]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(calibrate_fit, "AXIS_MISFIT_SIGMA", math.inf)  # never switch
        kept = fit_table("rippled", _Optics(), points, F_NUMBER)
    assert kept.axis == "polynomial"
    errs_kept = [_table_err_um(kept, float(z), rippled) for z in np.geomspace(1.5, 12.0, 25)]
    assert np.sqrt(np.mean(np.square(errs))) < np.sqrt(np.mean(np.square(errs_kept)))


def test_a_level_fit_follows_a_rippled_cam_with_a_leaning_cost() -> None:
    """A rippled cam swept with a cost that leans (not even in defocus), the bench's 23 depths:
    on the table fitted to each bracket's level (one constraint a depth, ½(T(a) + T(b)) = v),
    the estimator's own loop reads 2-9.5 m within 1.2 µm of v rms (0.62 here); on the table
    fitted to the bracket's two ends (the default) the same sweeps read 4.7 µm off: the ends'
    width is the axis's own, echoed back. (Noise seed 1; seeds 0-4: levels 0.50-1.75, ends
    0.30-4.71 µm, docs/estimation.md §20.)"""
    rng = np.random.default_rng(1)
    rippled = _rippled(0.12)
    points = [_point(z, rng, skew=0.5, truth=rippled) for z in DEFAULT_DEPTHS_M]
    levels = fit_table("levels", _Optics(), points, F_NUMBER, levels=True)
    assert levels.axis == "whole model"
    assert all(p.rule == "bracket level" for p in levels.model_points)
    ends = fit_table("ends", _Optics(), points, F_NUMBER)
    on_levels = _loop_err_um(levels, rippled, 0.5)
    assert on_levels < 1.2
    assert _loop_err_um(ends, rippled, 0.5) > 2.0 * on_levels


def test_the_mean_smoothing_spline_is_scipys_on_points_and_fits_means_of_pairs() -> None:
    """The spline fitted to means of two values: on points (both settings equal) it is
    ``make_smoothing_spline``; on pairs of a known smooth function's means it recovers them."""
    from scipy.interpolate import make_smoothing_spline

    rng = np.random.default_rng(0)
    u = np.sort(rng.uniform(0.0, 1.0, 20))
    r = np.sin(3.0 * u) + 0.01 * rng.standard_normal(20)
    w = np.ones(20)
    mine = calibrate_model._mean_smoothing_spline(np.stack([u, u], axis=1), r, w, 1e-5)
    ref = make_smoothing_spline(u, r, w=w, lam=1e-5)
    x = np.linspace(0.0, 1.0, 101)
    assert np.max(np.abs(mine(x) - ref(x))) < 1e-5
    pairs = np.stack([u, np.minimum(u + 0.2, 1.0)], axis=1)
    means = 0.5 * (np.sin(3.0 * pairs[:, 0]) + np.sin(3.0 * pairs[:, 1]))
    fit = calibrate_model._mean_smoothing_spline(pairs, means, w, 1e-9)
    assert np.max(np.abs(0.5 * (fit(pairs[:, 0]) + fit(pairs[:, 1])) - means)) < 1e-4


def _loop_err_um(table: TableFit, truth: Lens, skew: float) -> float:
    """RMS over 2-9.5 m of where the estimator's loop (plan_burst + fit_burst, re-centred until
    it settles) reads a static target on ``table``, swept on the lens ``truth`` (µm of v)."""
    lens = table.lens
    errs = []
    for z in np.geomspace(2.0, 9.5, 12):
        v0 = truth.v_from_depth(float(z))
        z_hat = float(z) * 1.02
        for _ in range(40):
            settings = plan_burst(lens, 0, z_hat, None)
            cost = _cost(truth.v_from_counts_array(np.array(settings, dtype=np.float64)), v0, skew)
            fit = fit_burst(
                [lens.v_from_counts(c) for c in settings], list(cost), list(1e-6 * cost), lens
            )
            assert fit.accepted, fit.reason
            assert fit.z_m is not None
            z_hat = fit.z_m
        errs.append((lens.v_from_depth(z_hat) - lens.v_from_depth(float(z))) * 1e3)
    return float(np.sqrt(np.mean(np.square(errs))))


def _table_err_um(table: TableFit, z_m: float, truth: Lens = TRUTH) -> float:
    c = truth.counts_for_depth(z_m)
    return float((table.lens.v_from_counts(c) - truth.v_from_counts(c)) * 1e3)
