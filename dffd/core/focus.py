"""Focus cost (2), the burst parabola fit and burst planning (DESIGN §2, §4; docs/estimation.md).

The cost model ``g(v0) = a (v0 − v)² + c`` holds in the lens-to-sensor distance ``v0`` (not in
focus counts): every fit is done in ``v`` through the lens table. Fits are computed in the
normalised coordinate ``x = (v0 − v_mid) / h`` (``h`` the half-width of the bracket) because
``v0`` is ~31 mm while the bracket is ~0.1 mm: a polynomial in raw ``v0`` is ill-conditioned.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core.lens import Lens

REASON_OK = "ok"


@dataclass(frozen=True, slots=True)
class FitConfig:
    """Acceptance checks of a burst fit."""

    vertex_margin: float = 0.5  # accept a vertex up to this fraction of h outside the bracket
    max_chi: float = 4.0  # with > 3 settings: reject when the RMS normalised residual exceeds it
    max_rel_sigma_v: float = 0.5  # reject when σ(v̂) exceeds this fraction of the half-bracket


@dataclass(frozen=True, slots=True)
class PlanConfig:
    """Burst planning: bracket half-width from the outer blur and from the depth uncertainty."""

    outer_blur_px: float = 3.0  # blur-circle radius at the outer settings (conditioning optimum)
    n_sigma: float = 2.5  # the bracket must cover ẑ ± n_sigma σ
    max_outer_blur_px: float = 8.0  # beyond this small targets blur into blobs: cap the bracket
    default_f_number: float = 2.8  # used when the lens file does not state f_number
    depth_range_m: tuple[float, float] = (1.5, 12.0)  # initial bracket when nothing is known


@dataclass(frozen=True, slots=True)
class BurstFit:
    """Result of fitting ``g = α v0² + β v0 + γ`` to one burst (α in 1/mm², v in mm)."""

    alpha: float
    v_hat_mm: float
    residual: float  # RMS of normalised residuals (0 with exactly three settings)
    accepted: bool
    reason: str  # "ok", a flag on an accepted fit, or why it was rejected
    z_m: float | None
    sigma_m: float | None
    sigma_v_mm: float


def focus_cost(
    peak_sq: npt.NDArray[np.float64], trim_fraction: float = 0.1
) -> tuple[float, float] | None:
    """Cost (2) from per-normal max ``||∇I||²`` (NaN = no edge): (g, σ_g) or None.

    Trimmed mean over the valid normals (``trim_fraction`` dropped at each end); σ_g is the
    standard error of that mean carried through the inverse.
    """
    vals = np.sort(peak_sq[np.isfinite(peak_sq)])
    n = len(vals)
    if n < 8:
        return None
    cut = int(trim_fraction * n)
    kept = vals[cut : n - cut] if n - 2 * cut >= 4 else vals
    mean = float(kept.mean())
    if mean <= 0:
        return None
    se = float(kept.std(ddof=1)) / math.sqrt(len(kept))
    g = 1.0 / mean
    return g, g * se / mean


def fit_burst(
    v_mm: Sequence[float],
    g: Sequence[float],
    sigma_g: Sequence[float],
    lens: Lens,
    config: FitConfig | None = None,
) -> BurstFit:
    """Fit the cost parabola to a burst; closed form for three settings, WLS for more."""
    cfg = config if config is not None else FitConfig()
    v = np.asarray(v_mm, dtype=np.float64)
    y = np.asarray(g, dtype=np.float64)
    s = np.maximum(np.asarray(sigma_g, dtype=np.float64), 1e-12 * np.abs(y).max(initial=1.0))
    if len(np.unique(np.round(v, 9))) < 3:
        return _rejected("fewer than three distinct focus settings")
    lo, hi = float(v.min()), float(v.max())
    mid, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    x = (v - mid) / h
    design = np.column_stack([x * x, x, np.ones_like(x)])
    w = 1.0 / s
    a = design * w[:, None]
    coef, *_ = np.linalg.lstsq(a, y * w, rcond=None)
    cov = np.linalg.inv(a.T @ a)
    res = (y - design @ coef) * w
    dof = len(y) - 3
    chi = float(np.sqrt(np.mean(res**2))) if dof > 0 else 0.0
    if dof > 0:
        cov = cov * max(1.0, float(res @ res) / dof)
    a2, a1, a0 = (float(c) for c in coef)
    alpha = a2 / (h * h)
    if a2 <= 0:
        return _rejected("alpha <= 0: the cost has no minimum in the bracket", alpha=alpha)
    xv = -a1 / (2 * a2)
    grad = np.array([a1 / (2 * a2 * a2), -1 / (2 * a2), 0.0])
    sigma_x = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
    v_hat = mid + h * xv
    sigma_v = h * sigma_x
    c_min = a0 - a1 * a1 / (4 * a2)
    reason = REASON_OK
    if abs(xv) > 1 + cfg.vertex_margin:
        return _rejected("vertex far outside the bracket", alpha, v_hat, chi, sigma_v)
    if abs(xv) > 1:
        reason = "vertex outside the bracket (extrapolated)"
    if dof > 0 and chi > cfg.max_chi:
        return _rejected("poor residual", alpha, v_hat, chi, sigma_v)
    if c_min <= 0:
        return _rejected("cost at the vertex <= 0", alpha, v_hat, chi, sigma_v)
    if sigma_x > cfg.max_rel_sigma_v:
        return _rejected(
            "ill-conditioned: vertex uncertain across the bracket", alpha, v_hat, chi, sigma_v
        )
    if v_hat <= lens.focal_length_mm:
        return _rejected("vertex at or beyond infinity focus", alpha, v_hat, chi, sigma_v)
    z = lens.depth_from_v(v_hat)
    sigma_z = abs(lens.dz_dv(v_hat)) * sigma_v
    return BurstFit(
        alpha, v_hat, chi, accepted=True, reason=reason, z_m=z, sigma_m=sigma_z, sigma_v_mm=sigma_v
    )


def plan_burst(
    lens: Lens,
    current_counts: int,
    z_hat_m: float | None,
    sigma_m: float | None,
    config: PlanConfig | None = None,
) -> tuple[int, int, int]:
    """Three focus counts bracketing the predicted sharp setting, ordered to minimise travel.

    Half-width in ``v``: the larger of the spacing that gives ``outer_blur_px`` of blur at the
    outer settings (a constant in ``v``, i.e. a depth-dependent spacing in depth and in counts)
    and ``n_sigma`` times the depth uncertainty mapped to ``v`` (``dv/dz ∝ 1/z²``); capped at
    ``max_outer_blur_px``. Without a prediction the bracket spans ``depth_range_m``. The bracket
    is shifted, not shrunk, where it meets the end of the lens table. Travel: visit the end
    nearest ``current_counts`` first, then the middle, then the other end.
    """
    cfg = config if config is not None else PlanConfig()
    n_f = lens.f_number if lens.f_number is not None else cfg.default_f_number
    vmin, vmax = lens.v_range_mm
    per_px = lens.pixel_pitch_mm * n_f * 2.0 / lens.focal_length_mm  # mm of v per px blur / v
    if z_hat_m is None or not math.isfinite(z_hat_m):
        near, far = cfg.depth_range_m
        v_lo, v_hi = lens.v_from_depth(far), lens.v_from_depth(near)
        v_c, h = 0.5 * (v_lo + v_hi), 0.5 * (v_hi - v_lo)
    else:
        v_c = lens.v_from_depth(max(z_hat_m, 2 * lens.focal_length_mm / 1000.0))
        h_blur = cfg.outer_blur_px * per_px * v_c
        h_cap = cfg.max_outer_blur_px * per_px * v_c
        sig_v = 0.0 if sigma_m is None else abs(lens.dz_dv(v_c)) ** -1 * sigma_m
        h = min(max(h_blur, cfg.n_sigma * sig_v), h_cap)
    h = min(h, 0.5 * (vmax - vmin))
    v_c = min(max(v_c, vmin + h), vmax - h)
    counts = [lens.counts_from_v(v_c - h), lens.counts_from_v(v_c), lens.counts_from_v(v_c + h)]
    counts.sort()
    # keep three distinct settings even where the table is coarse
    counts[1] = max(counts[1], counts[0] + 1)
    counts[2] = max(counts[2], counts[1] + 1)
    lo_c, _, hi_c = counts
    if abs(current_counts - hi_c) < abs(current_counts - lo_c):
        counts.reverse()
    return counts[0], counts[1], counts[2]


def _rejected(
    reason: str,
    alpha: float = math.nan,
    v_hat: float = math.nan,
    residual: float = math.nan,
    sigma_v: float = math.nan,
) -> BurstFit:
    return BurstFit(
        alpha,
        v_hat,
        residual,
        accepted=False,
        reason=reason,
        z_m=None,
        sigma_m=None,
        sigma_v_mm=sigma_v,
    )
