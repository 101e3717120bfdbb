"""The lens table of ``dffd calibrate``: the focus model refitted where the estimator's closed
loop reads each sweep, tabulated densely.

Pure numerics (no rig, no I/O), shared by the lab procedure and ``--sim``
(:mod:`dffd.calibrate_procedure`). A sweep's least-squares vertex is
:mod:`dffd.calibrate_parabola`, the focus model :mod:`dffd.calibrate_model`, the depth point
:mod:`dffd.calibrate_types` (all three split from this module).

Lens table (:func:`fit_table`). A first model goes through the sweeps' least-squares vertices
(in counts) and the infinity anchor at the far end of the focus range. Then, pass after pass,
each sweep is read through the latest model's polynomial as the v axis where the estimator's
closed loop settles on it (:func:`dffd.calibrate_vertex.closed_loop_vertex`: the burst bracket
whose two ends cost the same), and the model is refitted through the two ends of each settled
bracket, at v − h and v + h of the depth: on that table the loop settles at v and reads the
calibrated depth whatever the lens's point-spread function (docs/estimation.md §16). The table
is the model every :data:`TABLE_STEP_COUNTS` over the focus range where it stays monotone. With
fewer than :data:`MIN_MODEL_DEPTHS` depths the table is the points themselves
(:func:`lens_from_points`). Repeated sweeps of one depth are combined into one point
(:func:`combine_sweeps`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dffd.calibrate_model import FocusModel, ModelFit, fit_anchored
from dffd.calibrate_parabola import fit_vertex
from dffd.calibrate_types import CalibrationError, DepthPoint, FocusOptics
from dffd.calibrate_vertex import closed_loop_vertex
from dffd.core.focus import PlanConfig
from dffd.core.lens import MM_PER_M, Lens

FloatArray = npt.NDArray[np.float64]

TABLE_STEP_COUNTS = 256  # spacing of the written table's rows (PCHIP of a smooth model: exact)
# Half-width of the vertex window of the refit in v, in px of blur radius: the estimator's own
# burst bracket (PlanConfig.outer_blur_px, 3 px), where a measure's lean on a lens is the one its
# bursts fit. Chosen on the reference optics (paper-circle seed 1, 60 s, peak_gradient): 1 px ->
# table 14 mm rms, bench 28 mm; 3 px -> 3.6 mm, 8.8 mm (true table: 8.0 mm). On the aberrated
# optics the bench is the same with 1 or 3 px (docs/estimation.md §10).
VERTEX_WINDOW_BLUR_PX = PlanConfig().outer_blur_px
# Refit passes through the latest model's polynomial (the bracket ends move < 0.1 µm after ~4).
# The axis is the polynomial, not the residual spline: through the spline the passes feed each
# reading's scatter back into the axis (reference optics seed 1: table 2.3 -> 11.1 mm rms).
REFIT_PASSES = 8
SETTLED_SIGMA = 0.05  # the passes stop when no bracket end moves by more than this × its σ
# The fit missing its own bracket ends by more than this many of their σ (rms) means the axis
# misses the focus curve: the passes go on through the whole model (polynomial and spline). The
# same limit as a depth the others predict badly (calibrate_check.REPEAT_SIGMA).
AXIS_MISFIT_SIGMA = 3.0
MIN_MODEL_DEPTHS = 4  # fewer depths: the table is the measured points themselves
# Repeated sweeps of one depth (combine_sweeps): with three or more, a sweep whose vertex is more
# than this many of its σ from the others' median is dropped (a disturbed sweep: the target
# knocked, a lighting flicker); the combined σ is scaled up by the sweeps' own disagreement.
SWEEP_OUTLIER_SIGMA = 4.0
# fit_table(levels=True): the model is fitted to each settled bracket's level — the table's
# mean v over its two ends is the depth's v — instead of to the two ends at v ∓ h, whose width
# on the axis read is the axis's own (docs/estimation.md §18, §20). Not the default: measured
# worse on held-out sweeps of the aberrated optics (§20).
LEVEL_NEWTON_STEPS = 4  # the mean-power correction converges quadratically from P(v)


@dataclass(frozen=True, slots=True)
class TableFit:
    """The calibrated table: the depth points, the smooth model and its residuals."""

    points: tuple[DepthPoint, ...]
    fit: ModelFit | None  # None with fewer than MIN_MODEL_DEPTHS depths
    lens: Lens
    # the points the model was fitted to: the settled brackets' ends (two a depth), or the
    # depth points themselves (empty: ``points``)
    fit_points: tuple[DepthPoint, ...] = ()
    # the refit passes' v axis: "polynomial" (the model's polynomial), or "whole model"
    # (polynomial and spline) when the polynomial axis missed its own bracket ends by more than
    # AXIS_MISFIT_SIGMA (a cam ripple); and that misfit (rms, in the ends' σ; NaN: no refit)
    axis: str = "polynomial"
    axis_misfit_sigma: float = math.nan

    @property
    def model_points(self) -> tuple[DepthPoint, ...]:
        """The points the focus model went through (``fit``'s per-point figures are theirs)."""
        return self.fit_points or self.points

    def residual_lines(self) -> list[str]:
        """One line per depth: where the closed loop reads its sweep (counts, v), how, and the
        model's residual at the points it was fitted to there (for the CLI)."""
        lines = []
        fitted = self.model_points
        for p in self.points:
            line = f"z = {p.z_m:6.2f} m  read at counts {p.at:9.1f}"
            if not math.isnan(p.sigma_counts):
                line += f" ± {p.sigma_counts:5.1f}"
            line += f"  v = {p.v_mm:.6f} mm ({p.rule})"
            if self.fit is not None:
                mine = [i for i, q in enumerate(fitted) if q.placed_m == p.placed_m]
                if not mine:
                    line += "  not fitted (the bracket meets the end of the focus range)"
                for i in mine:
                    q = fitted[i]
                    where = (
                        ""
                        if q is p or q.rule != "bracket end"
                        else (f" at v {q.v_mm - p.v_mm:+.4f} mm")
                    )
                    line += f"; residual{where} {self.fit.residual_v_um[i]:+6.3f} µm of v" + (
                        "" if self.fit.used[i] else " REJECTED (outlier: re-measure)"
                    )
            lines.append(line)
        if self.fit is not None:
            m = self.fit
            spline = (
                ""
                if m.model.spline is None
                else (f" + smoothing spline (λ = {m.model.spline_lam:.0e})")
            )
            lines.append(
                f"focus model: P(counts) polynomial of degree {m.model.degree}{spline} "
                f"(cross-validated), {sum(m.used)} of {len(m.used)} points; residual rms "
                f"{m.rms_v_um:.3f} µm of v, {m.rms_depth_mm:.1f} mm of depth; leave-one-depth-out "
                f"prediction rms {m.loo_rms_v_um:.3f} µm of v"
            )
        return lines


def fit_table(
    name: str,
    rig: FocusOptics,
    points: list[DepthPoint],
    f_number: float | None = None,
    window_blur_px: float = VERTEX_WINDOW_BLUR_PX,
    *,
    levels: bool = False,
) -> TableFit:
    """The calibrated lens: a smooth focus model through the depth points (vertices refitted in
    v through it, on ± ``window_blur_px`` of blur), tabulated densely; with fewer than
    MIN_MODEL_DEPTHS depths, the points themselves. ``levels``: fit each settled bracket's
    level (the mean of the table over its two ends) instead of its two ends, through the whole
    model as the axis (docs/estimation.md §20)."""
    f, pitch = rig.focal_length_mm, rig.pixel_pitch_mm
    groups = _by_depth(points)
    points = [combine_sweeps(g) for g in groups]
    if len(points) < MIN_MODEL_DEPTHS:
        lens = lens_from_points(name, f, pitch, points)
        return TableFit(tuple(points), None, _with_f_number(lens, f_number, rig.zoom_counts))
    _check_monotone(points)
    span = (float(rig.focus_range[0]), float(rig.focus_range[1]))
    fit_points = points
    # The model is anchored at P = 0 at the far end of the focus range (focus at infinity, the
    # VISCA camera's datasheet, docs/design.md §6): the estimator's brackets at 10 m reach far
    # past the last calibrated depth, and there an unanchored model's cam ripple is free
    # (aberrated optics, seed 1: a true 100 m read as 44 m; bench 771 -> 483 mm ss RMS on 60 s,
    # true table 481 mm; reference unchanged).
    model = fit_anchored(points, f, span)
    # Refit passes: each sweep read where the estimator's closed loop settles on it, through
    # the latest model as the v axis (the estimator plans and fits its bursts in the table's v).
    # A sweep read there gives the two ends of its settled bracket, counts a and b of equal
    # cost: the table must map them to v − h and v + h of the depth (then the closed loop, on
    # this table, settles at v and reads the depth). The bracket ends of the nearer depths
    # reach to ~f + 10 µm (a 10 m target), where no target can be calibrated: the table near
    # infinity is measured where the estimator uses it (docs/estimation.md §16). Depths whose
    # bracket meets the end of the focus range (beyond ~11 m) give no pair and are not fitted.
    n_f = f_number if f_number is not None else PlanConfig().default_f_number
    per_px = pitch * n_f * 2.0 / f  # mm of v per px of blur radius, per mm of v (plan_burst)
    model, refit, fit_points = _settle(
        groups, model, points, span, per_px * window_blur_px, levels=levels
    )
    # A focus curve the polynomial cannot follow (a cam ripple) leaves the bracket ends of
    # neighbouring depths inconsistent through the polynomial axis: the fit then misses its own
    # points by many of their σ. Only then the passes go on with the whole model (polynomial and
    # spline) as the axis; through the spline a model that needs none feeds the readings'
    # scatter back (reference optics: misfit 0.4-0.8 σ rms, polynomial axis kept).
    # Levels fix no width: their pairs must be read through the table itself (its own width),
    # or the estimator's brackets on it are not the pairs calibrated (a polynomial axis on a
    # rippled cam: widths 20 % off; held-out aberrated sweeps read 86-94 mm rms, §20).
    misfit = _misfit_sigma(model, fit_points)
    axis = "polynomial"
    if misfit > AXIS_MISFIT_SIGMA or levels:
        axis = "whole model"
        model, refit, fit_points = _settle(
            groups, model, points, span, per_px * window_blur_px, spline_axis=True,
            levels=levels,
        )  # fmt: skip
    ats = [p.at for p in (*refit, *fit_points)]
    grid, v = _tabulate(model.model, (min(ats), max(ats)), span)
    lens = Lens(
        name, f, pitch, tuple(int(c) for c in grid), tuple(float(x) for x in v),
        f_number=f_number, zoom_counts=rig.zoom_counts,
        table_sigma_v_mm=model.table_sigma_v_um / 1000.0,
    )  # fmt: skip
    return TableFit(tuple(refit), model, lens, tuple(fit_points), axis, misfit)


def lens_from_points(
    name: str, focal_length_mm: float, pixel_pitch_mm: float, points: list[DepthPoint]
) -> Lens:
    """A :class:`Lens` from the sweep results; raises CalibrationError if not monotone."""
    _check_monotone(points)
    pts = sorted(points, key=lambda p: p.counts)
    counts = [p.counts for p in pts]
    v = [p.v_mm for p in pts]
    return Lens(name, focal_length_mm, pixel_pitch_mm, tuple(counts), tuple(v))


def combine_sweeps(sweeps: list[DepthPoint]) -> DepthPoint:
    """One point from repeated sweeps of one depth: the inverse-variance mean of their vertices
    (with three or more, a sweep beyond SWEEP_OUTLIER_SIGMA of the others' median dropped), its
    σ scaled by their disagreement when they scatter more than their σ says."""
    if len(sweeps) == 1:
        return sweeps[0]
    x = np.array([p.at for p in sweeps])
    sigma = np.array([p.sigma_counts for p in sweeps])
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, float(np.nanmedian(sigma)))
    if not np.isfinite(sigma).all():
        sigma = np.full(len(x), max(float(np.std(x)), 1.0))
    keep = np.ones(len(x), dtype=bool)
    if len(x) >= 3:
        off = np.abs(x - float(np.median(x))) / sigma
        worst = int(np.argmax(off))
        keep[worst] = off[worst] <= SWEEP_OUTLIER_SIGMA
    w = 1.0 / sigma[keep] ** 2
    mean = float(np.sum(w * x[keep]) / np.sum(w))
    dof = int(keep.sum()) - 1
    chi2 = float(np.sum(w * (x[keep] - mean) ** 2)) / dof if dof > 0 else 0.0
    sigma_mean = math.sqrt(1.0 / float(np.sum(w)) * max(chi2, 1.0))
    nearest = sweeps[int(np.argmin(np.where(keep, np.abs(x - mean), np.inf)))]
    return dataclasses.replace(
        nearest,
        counts=round(mean),
        counts_exact=mean,
        sigma_counts=sigma_mean,
        n_sweeps=len(sweeps),
        spread_counts=float(np.std(x, ddof=1)),
        sweeps_chi2=chi2,
    )


# -- private helpers --------------------------------------------------------------------------
def _check_monotone(points: list[DepthPoint]) -> None:
    pts = sorted(points, key=lambda p: p.at)
    counts = [p.counts for p in pts]
    v = [p.v_mm for p in pts]
    steps = [b - a for a, b in itertools.pairwise(v)]
    monotone = all(d > 0 for d in steps) or all(d < 0 for d in steps)
    if len(set(counts)) != len(counts) or not monotone:
        raise CalibrationError(
            "the sharpest settings are not monotone in depth "
            f"(counts {counts}, v {[round(x, 4) for x in v]}); use depths further apart"
        )


def _by_depth(points: list[DepthPoint]) -> list[list[DepthPoint]]:
    """The points grouped by depth (repeated sweeps of one depth together), in depth order."""
    groups: dict[float, list[DepthPoint]] = {}
    for p in points:
        groups.setdefault(p.z_m, []).append(p)
    return [groups[z] for z in sorted(groups)]


def _closed_loop_read(
    point: DepthPoint,
    model: Any,
    half_width_mm: float,
    span: tuple[float, float],
    *,
    levels: bool = False,
) -> tuple[DepthPoint, ...]:
    """``point``'s sweep read through ``model`` as the v axis: where the estimator's closed
    loop settles with a bracket of ± ``half_width_mm`` (:func:`closed_loop_vertex`) — the
    bracket's two ends (points at v ∓ h of the depth) and its centre (the depth); or, where the
    bracket meets the end of the focus range ``span`` or the sweep does not reach it, only the
    depth point, read at the pinned bracket or at the least-squares vertex of the window. With
    ``levels`` the two ends come as one level point (:attr:`DepthPoint.pair_at`) and the
    centre."""
    if len(point.sweep) < 3:
        return (point,)
    c, g, s = (np.array(col) for col in zip(*point.sweep, strict=True))
    v = model.v_mm(c)
    order = np.argsort(v)
    found = fit_vertex(v[order], g[order], s[order], half_width_mm)
    if found is None:
        return (point,)
    lo, hi = float(c.min()), float(c.max())

    def at_v(x: float, sigma_v: float, rule: str, offset_mm: float = 0.0) -> DepthPoint:
        """The point at ``x`` (the model's v) standing for the depth's v + ``offset_mm``."""
        at = model.counts_for_v(x, lo, hi)
        slope = abs(float(np.gradient(v, c)[int(np.argmin(np.abs(c - at)))]))
        sigma = sigma_v / slope if slope > 0 else point.sigma_counts
        v_mm = point.v_mm + offset_mm
        f = model.focal_length_mm
        # the depth in focus at v_mm (negative beyond infinity: P = 1/z < 0)
        z_m = point.z_m if offset_mm == 0 else f * v_mm / (v_mm - f) / MM_PER_M
        return dataclasses.replace(
            point, z_m=z_m, v_mm=v_mm, counts=round(at), counts_exact=at, sigma_counts=sigma,
            rule=rule, target_m=point.placed_m,
        )  # fmt: skip

    ends = (float(model.v_mm(span[0])), float(model.v_mm(span[1])))
    loop = closed_loop_vertex(v, g, s, half_width_mm, start=found.x, ends=ends)
    if loop is None:
        return (at_v(found.x, found.sigma, "least squares"),)
    if loop.pinned:
        return (at_v(loop.x, loop.sigma, "closed loop, pinned"),)
    h = half_width_mm
    if levels:
        a = at_v(loop.x - h, loop.sigma, "bracket end", -h)
        b = at_v(loop.x + h, loop.sigma, "bracket end", h)
        level = dataclasses.replace(
            at_v(loop.x, loop.sigma, "bracket level"),
            counts_exact=a.at,
            pair_at=b.at,
            z_m=_level_depth_m(point.v_mm, model.power_dpt([a.at, b.at]), model.focal_length_mm),
        )
        return (level, at_v(loop.x, loop.sigma, "closed loop"))
    return (
        at_v(loop.x - h, loop.sigma, "bracket end", -h),
        at_v(loop.x + h, loop.sigma, "bracket end", h),
        at_v(loop.x, loop.sigma, "closed loop"),
    )


def _settle(
    groups: list[list[DepthPoint]],
    model: ModelFit,
    points: list[DepthPoint],
    span: tuple[float, float],
    h_per_v: float,
    *,
    spline_axis: bool = False,
    levels: bool = False,
) -> tuple[ModelFit, list[DepthPoint], list[DepthPoint]]:
    """Refit passes until the bracket ends stop moving: each sweep read through the model (its
    polynomial, or the whole model with ``spline_axis``), the model refitted through the ends;
    the model, the depth points (where each depth is read) and the points it was fitted to."""
    f = model.model.focal_length_mm
    refit, fit_points = points, points
    structure: tuple[int, float] | None = None
    for k in range(REFIT_PASSES):
        mapping = model.model if spline_axis else dataclasses.replace(model.model, spline=None)
        ends: list[DepthPoint] = []
        centres: list[DepthPoint] = []
        for g in groups:
            reads = [
                _closed_loop_read(p, mapping, h_per_v * p.v_mm, span, levels=levels) for p in g
            ]
            level_reads = [r for r in reads if len(r) == 2]
            pairs = [r for r in reads if len(r) == 3]
            if level_reads:
                ends.append(_combine_levels([r[0] for r in level_reads]))
                centres.append(combine_sweeps([r[1] for r in level_reads]))
            elif pairs:
                ends += [
                    combine_sweeps([r[0] for r in pairs]),
                    combine_sweeps([r[1] for r in pairs]),
                ]
                centres.append(combine_sweeps([r[2] for r in pairs]))
            else:
                centres.append(combine_sweeps([r[-1] for r in reads]))
        if len({p.placed_m for p in ends}) < MIN_MODEL_DEPTHS:
            break
        settled = len(ends) == len(fit_points) and all(
            max(abs(a.at - b.at), abs(a.other - b.other)) < SETTLED_SIGMA * a.sigma_counts
            for a, b in zip(ends, fit_points, strict=True)
        )
        refit, fit_points = centres, ends
        # the model's structure (degree, smoothing) is chosen on the first and the last pass
        last = settled or k == REFIT_PASSES - 1
        model = fit_anchored(ends, f, span, None if last else structure)
        structure = (model.model.degree, model.model.spline_lam)
        if settled:
            break
    return model, refit, fit_points


def _level_depth_m(v_mm: float, power_ab: FloatArray, f: float) -> float:
    """The depth (m) whose focus power P̄ is a bracket level's mean power: the table's mean v
    over two powers P̄ ∓ d (d their half-difference on the axis read) is ``v_mm`` exactly — the
    mean of v is not v of the mean power (v is convex in P: ~0.3 µm at h = 90 µm)."""
    d = 0.5 * float(power_ab[1] - power_ab[0])
    power = (1.0 / f - 1.0 / v_mm) * MM_PER_M  # dioptres: P of v_mm itself
    for _ in range(LEVEL_NEWTON_STEPS):
        va, vb = (1.0 / (1.0 / f - q / MM_PER_M) for q in (power - d, power + d))
        power -= (0.5 * (va + vb) - v_mm) / (0.5 * (va * va + vb * vb) / MM_PER_M)
    return 1.0 / power if power != 0 else math.inf


def _combine_levels(levels: list[DepthPoint]) -> DepthPoint:
    """One level from repeated sweeps of one depth: each end combined as a point
    (:func:`combine_sweeps`), the mean power kept from the sweep nearest the combined ends."""
    if len(levels) == 1:
        return levels[0]
    a = combine_sweeps(levels)
    b = combine_sweeps([dataclasses.replace(p, counts_exact=p.pair_at) for p in levels])
    return dataclasses.replace(a, pair_at=b.at)


def _misfit_sigma(model: ModelFit, points: list[DepthPoint]) -> float:
    """RMS of the model's residuals at ``points`` in units of their own σ (the points used)."""
    if len(points) != len(model.residual_v_um):
        return 0.0
    at = np.array([p.at for p in points])
    slope = np.abs(model.model.v_mm(at + 0.5) - model.model.v_mm(at - 0.5))  # mm per count
    sigma_um = np.array([p.sigma_counts for p in points]) * slope * 1e3
    r = np.asarray(model.residual_v_um) / sigma_um
    used = np.asarray(model.used) & np.isfinite(r)
    return float(np.sqrt(np.mean(r[used] ** 2))) if used.any() else 0.0


def _tabulate(
    model: FocusModel, measured: tuple[float, float], focus_range: tuple[float, float]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """The model every TABLE_STEP_COUNTS over the whole focus range: the estimator's brackets
    reach ~90 µm of v beyond the target (past 20 m towards infinity at 10 m), and a table that
    stops at the last calibrated depth shifts them off-centre (paper-circle: 8 -> 157 mm ss RMS
    with the true table cut to 1.2-20 m). Beyond the measured depths the model extrapolates
    while it stays monotone and in front of infinity (P > 0)."""
    lo, hi = sorted(focus_range)
    grid = np.unique(np.r_[np.arange(math.ceil(lo), hi, TABLE_STEP_COUNTS), math.floor(hi)])
    power = model.power_dpt(grid)
    v = model.v_mm(grid)
    inside = (grid >= measured[0]) & (grid <= measured[1])
    rising = np.diff(v) > 0
    first, last = int(np.flatnonzero(inside)[0]), int(np.flatnonzero(inside)[-1])
    if not (rising[first:last].all() or not rising[first:last].any()):
        raise CalibrationError(
            "the fitted focus model is not monotone over the calibrated range; check the "
            "depths printed with large residuals and re-measure them"
        )
    step_up = bool(rising[first]) if last > first else True
    while first > 0 and bool(rising[first - 1]) == step_up and power[first - 1] > 0:
        first -= 1
    while last < len(grid) - 1 and bool(rising[last]) == step_up and power[last + 1] > 0:
        last += 1
    return grid[first : last + 1].astype(np.int64), v[first : last + 1]


def _with_f_number(lens: Lens, f_number: float | None, zoom_counts: int | None) -> Lens:
    return dataclasses.replace(lens, f_number=f_number, zoom_counts=zoom_counts)
