"""How far a fitted lens table can be trusted, and which depths to sweep again (dffd calibrate).

Per calibrated depth (:func:`check_table`):

* the table's own σ: a parametric bootstrap of the focus model — each depth's vertex moved by
  its σ, the model of the same structure (degree, spline) refitted
  (:func:`dffd.calibrate_model.model_with_structure`), the spread of v at each setting;
* the leave-one-out residual: the depth's measured v against the table fitted without it, and
  that in units of the two σ combined (a z-score).

A depth the others predict worse than :data:`REPEAT_SIGMA` σ is swept again (a lab would
re-measure it; :func:`dffd.calibrate_procedure.calibrate_table`): once, and again (up to
:data:`MAX_SWEEPS`) while its sweeps disagree beyond their σ — sweep noise, which a third sweep
outvotes (:func:`dffd.calibrate_fit.combine_sweeps`); sweeps that agree with each other but not
with the table say the model misses something between the depths (a cam ripple: more depths,
not more sweeps). When the leave-one-out z-scores' RMS exceeds 1 the
table's σ is scaled up by it: the sweeps' own σ does not cover what the model misses.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.calibrate_fit import TableFit
from dffd.calibrate_model import FocusModel, model_v_mm, model_with_structure
from dffd.calibrate_types import DepthPoint, FocusOptics

FloatArray = npt.NDArray[np.float64]

# A depth whose leave-one-out residual exceeds this many σ is swept again. Chosen on the
# reference optics (paper-circle's camera, seeds 1-3, peak_gradient): once the refit's axis no
# longer follows the first pass's scatter the z-scores there stay within ±2.5 (docs/estimation.md
# §10); 3 leaves room for the tails of 15-23 depths and still catches a sweep 1 µm of v off.
REPEAT_SIGMA = 3.0
MAX_SWEEPS = 3  # sweeps of one depth at most (the first and two repeats)
# Repeated sweeps of one depth disagree when their χ² per degree of freedom exceeds this: more
# scatter than their σ (a 95 % point of χ² with 1-2 degrees of freedom is 3.0-3.8).
SWEEPS_DISAGREE_CHI2 = 4.0
# Depths set aside as suspects stop while this many remain to check them against (each gives
# its bracket's two ends: four depths and the infinity anchor hold a cubic and its
# leave-one-depth-out).
MIN_CHECKED_DEPTHS = 4
BOOTSTRAP_SAMPLES = 40  # resampled models (the σ's own relative error ~ 1/sqrt(2·40) = 11 %)
BOOTSTRAP_SEED = 0  # fixed: the same sweeps give the same table σ


@dataclass(frozen=True, slots=True)
class DepthCheck:
    """One calibrated depth: the table's σ there and how well the other depths predict it."""

    z_m: float
    sigma_v_um: float  # the table's 1σ at this depth (scaled by misfit_scale), µm of v
    sigma_depth_mm: float  # the same in depth
    loo_v_um: float  # measured v − the table fitted without this depth
    z_score: float  # loo_v_um over the vertex's and the table's σ combined (unscaled)
    n_sweeps: int
    spread_v_um: float  # the sweeps' vertices' standard deviation (NaN: one sweep)
    sweeps_chi2: float  # their χ² per degree of freedom (NaN: one sweep)


@dataclass(frozen=True, slots=True)
class TableCheck:
    """The table's uncertainty per depth and over its settings; the depths to sweep again."""

    depths: tuple[DepthCheck, ...]
    misfit_scale: float  # RMS leave-one-out z-score when above 1 (else 1): the σ's scale-up
    grid_counts: tuple[float, ...]  # the table's settings …
    grid_sigma_v_um: tuple[float, ...]  # … and its 1σ there (scaled), µm of v
    repeat: tuple[float, ...]  # depths (m) to sweep again

    def sigma_v_um_at(self, counts: float) -> float:
        """The table's 1σ (µm of v) at ``counts`` (interpolated over its settings)."""
        return float(np.interp(counts, self.grid_counts, self.grid_sigma_v_um))

    def lines(self) -> list[str]:
        """The uncertainty per depth and the verdict, for the CLI and the lens file."""
        out = []
        for d in self.depths:
            line = (
                f"z = {d.z_m:6.2f} m  table ± {d.sigma_v_um:.3f} µm of v "
                f"(± {d.sigma_depth_mm:.1f} mm of depth, 1σ); leave-one-out "
                f"{d.loo_v_um:+6.3f} µm ({d.z_score:+.1f} σ)"
            )
            if d.n_sweeps > 1:
                line += f"; {d.n_sweeps} sweeps, spread {d.spread_v_um:.3f} µm"
                if d.sweeps_chi2 > SWEEPS_DISAGREE_CHI2:
                    line += " (they disagree: sweep noise)"
            if not math.isfinite(d.z_score):
                line += " (not fitted: no closed-loop bracket inside the focus range)"
            if d.z_m in self.repeat:
                line += "  SWEEP AGAIN"
            out.append(line)
        scores = [d.z_score for d in self.depths if math.isfinite(d.z_score)]
        rms = math.sqrt(float(np.mean(np.square(scores)))) if scores else math.nan
        verdict = (
            f"table uncertainty (1σ): {min(d.sigma_depth_mm for d in self.depths):.1f}-"
            f"{max(d.sigma_depth_mm for d in self.depths):.1f} mm of depth over the calibrated "
            f"depths; leave-one-out z-scores rms {rms:.2f}"
        )
        if self.misfit_scale > 1.0:
            verdict += (
                f" > 1: σ scaled up ×{self.misfit_scale:.1f} (the model misses more than the "
                "sweeps' noise between the depths; if repeated sweeps agree, add depths there)"
            )
        out.append(verdict)
        return out


def check_table(table: TableFit, rig: FocusOptics) -> TableCheck:
    """The table's σ per depth (bootstrap), the leave-one-depth-out z-scores and the depths to
    sweep again; ``table`` must carry a model (at least MIN_MODEL_DEPTHS depths)."""
    if table.fit is None:
        raise ValueError("check_table needs a table fitted with a focus model")
    f = rig.focal_length_mm
    span = (float(rig.focus_range[0]), float(rig.focus_range[1]))
    like = table.fit.model
    fitted = list(table.model_points)
    points = list(table.points)  # one per depth: where the closed loop reads it
    depth_of = np.array([q.placed_m for q in fitted])
    sigma_fit = _sigmas(fitted)
    at = np.array([p.at for p in points])
    grid = np.asarray(table.lens.focus_counts, dtype=np.float64)
    sigma_grid = _bootstrap_sigma_v_um(
        fitted, sigma_fit, depth_of, f=f, span=span, like=like, counts=np.r_[grid, at]
    )
    sigma_table = sigma_grid[len(grid) :]
    slope = np.abs(np.gradient(like.v_mm(grid), grid))  # mm of v per count
    # each depth's own σ (its reading's; a depth's two bracket ends share it) and the table's
    fitted_depths = [p.placed_m for p in points if (depth_of == p.placed_m).any()]
    sigma_vertex = np.array(
        [
            float(np.mean(sigma_fit[depth_of == p.placed_m] * np.interp(
                [q.at for q in fitted if q.placed_m == p.placed_m], grid, slope
            ))) * 1e3
            if p.placed_m in fitted_depths
            else math.nan
            for p in points
        ]
    )  # fmt: skip
    sigma_both = np.sqrt(sigma_vertex**2 + sigma_table**2)
    # One bad depth bends every fit it is in, so every other depth's leave-one-out residual too
    # (6 depths, one placed 0.3 m off: all six were flagged). The worst beyond REPEAT_SIGMA is
    # set aside and the others checked without it, until none is beyond.
    aside = np.zeros(len(points), dtype=bool)
    fitted_mask = np.isfinite(sigma_vertex)
    while True:
        loo = _leave_one_depth_out_um(points, fitted, aside, f=f, span=span, like=like)
        z = loo / sigma_both
        worst = int(np.argmax(np.where(aside | ~fitted_mask, -np.inf, np.abs(z))))
        if abs(z[worst]) <= REPEAT_SIGMA or (~aside & fitted_mask).sum() <= MIN_CHECKED_DEPTHS:
            break
        aside[worst] = True
    scale = max(1.0, math.sqrt(float(np.mean(z[fitted_mask] ** 2)))) if fitted_mask.any() else 1.0
    depths = []
    repeat = []
    for i, p in enumerate(points):
        v = p.v_mm
        sigma_v = float(sigma_table[i]) * scale
        dz_dv = f * f / (v - f) ** 2  # |dz/dv| of the thin lens z = f v / (v − f)
        spread = p.spread_counts * float(np.interp(p.at, grid, slope)) * 1e3
        chi2 = p.sweeps_chi2
        depths.append(
            DepthCheck(
                p.z_m, sigma_v, sigma_v * 1e-3 * dz_dv, float(loo[i]), float(z[i]), p.n_sweeps,
                float(spread), chi2,
            )
        )  # fmt: skip
        # once swept again, the depth's σ carries its sweeps' disagreement (combine_sweeps) and
        # its z-score shrinks: sweeps that still disagree ask for another, whatever the z-score
        flagged = bool(aside[i]) if p.n_sweeps == 1 else chi2 > SWEEPS_DISAGREE_CHI2
        if flagged and p.n_sweeps < MAX_SWEEPS and fitted_mask[i]:
            repeat.append(p.z_m)
    return TableCheck(
        tuple(depths),
        scale,
        tuple(float(c) for c in grid),
        tuple(float(s) * scale for s in sigma_grid[: len(grid)]),
        tuple(repeat),
    )


def table_sigma_per_depth(table: TableFit, check: TableCheck) -> tuple[tuple[int, float], ...]:
    """The table's own standard error of v (mm) at each calibrated depth, as (counts where the
    closed loop reads it, σ) rows for the lens file (``Lens.table_sigma_v_at``).

    The one-number formula of :attr:`dffd.calibrate_fit.ModelFit.table_sigma_v_um` applied at
    each depth: σ_v² = max(loo² − res², 0)/2, with the depth's leave-one-depth-out error and the
    mean square of the model's residuals at its points (a rejected point's as 0). Nothing is
    chosen; at a depth the model misses (a near-end ripple, an outlier sweep) the term is what
    the data say there, not a whole-table average that is 3x too wide at 3-7 m and too narrow
    at 1.5-2 m (docs/estimation.md §25). Depths without a fitted point are left out."""
    if table.fit is None:
        return ()
    fit = table.fit
    fitted = table.model_points
    rows: dict[int, float] = {}
    for p, d in zip(table.points, check.depths, strict=True):
        mine = [
            fit.residual_v_um[i] if fit.used[i] else 0.0
            for i, q in enumerate(fitted)
            if q.placed_m == p.placed_m
        ]
        if not mine or not math.isfinite(d.loo_v_um):
            continue
        res2 = float(np.mean(np.square(mine)))
        sigma_um = math.sqrt(max(d.loo_v_um**2 - res2, 0.0) / 2.0)
        rows[round(p.at)] = sigma_um / 1000.0
    return tuple(sorted(rows.items()))


# -- private helpers --------------------------------------------------------------------------
def _sigmas(points: list[DepthPoint]) -> FloatArray:
    """The points' σ in counts (a point without one: the median of the others)."""
    sigma = np.array([p.sigma_counts for p in points])
    ok = np.isfinite(sigma) & (sigma > 0)
    fallback = float(np.median(sigma[ok])) if ok.any() else 1.0
    return np.asarray(np.where(ok, sigma, fallback), dtype=np.float64)


def _leave_one_depth_out_um(
    points: list[DepthPoint],
    fitted: list[DepthPoint],
    aside: npt.NDArray[np.bool_],
    *,
    f: float,
    span: tuple[float, float],
    like: FocusModel,
) -> FloatArray:
    """Per depth: the mean of its fitted points' v less the model fitted without that depth
    and without the depths set ``aside`` (NaN: a depth not in the fit)."""
    out = []
    aside_depths = {p.placed_m for p, a in zip(points, aside, strict=True) if a}
    for p in points:
        mine = [q for q in fitted if q.placed_m == p.placed_m]
        if not mine:
            out.append(math.nan)
            continue
        others = [q for q in fitted if q.placed_m != p.placed_m and q.placed_m not in aside_depths]
        model = model_with_structure(others, f, span, like)
        out.append(float(np.mean([(q.v_mm - model_v_mm(model, q)) * 1e3 for q in mine])))
    return np.asarray(out, dtype=np.float64)


def _bootstrap_sigma_v_um(
    points: list[DepthPoint],
    sigma_counts: FloatArray,
    depth_of: FloatArray,
    *,
    f: float,
    span: tuple[float, float],
    like: FocusModel,
    counts: FloatArray,
) -> FloatArray:
    """σ (µm) of the model's v at ``counts`` over models refitted to points moved by their σ
    (the points of one depth together: a sweep's bracket ends move with its reading)."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    depths = np.unique(depth_of)
    samples = []
    for _ in range(BOOTSTRAP_SAMPLES):
        draw = dict(zip(depths.tolist(), rng.normal(size=len(depths)).tolist(), strict=True))
        moved = [
            dataclasses.replace(
                p,
                counts_exact=p.at + draw[d] * s,
                pair_at=p.pair_at + draw[d] * s,  # a level's two ends move together (NaN: none)
            )
            for p, s, d in zip(points, sigma_counts, depth_of.tolist(), strict=True)
        ]
        samples.append(model_with_structure(moved, f, span, like).v_mm(counts))
    return np.asarray(np.std(np.array(samples), axis=0, ddof=1) * 1e3, dtype=np.float64)
