"""Focus cost (2), the burst parabola fit and burst planning (design.md §3, §5; docs/estimation.md).

The cost model ``g(v0) = a (v0 − v)² + c`` holds in the lens-to-sensor distance ``v0`` (not in
focus counts): every fit is done in ``v`` through the lens table. Fits are computed in the
normalised coordinate ``x = (v0 − v_mid) / h`` (``h`` the half-width of the bracket) because
``v0`` is ~31 mm while the bracket is ~0.1 mm: a polynomial in raw ``v0`` is ill-conditioned.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from dffd.core import kernel_dispatch
from dffd.core.lens import Lens, VertexResponse
from dffd.literals import FocusMeasure

REASON_OK = "ok"

DEFAULT_FOCUS_MEASURE: FocusMeasure = "edge_variance"

# Window (in pooled edge spreads) of the edge moment that ``debiased_peak`` debiases the peak
# gradient against: wider than the ``edge_variance`` measure's 3, because a window of a few
# spreads cuts more of an asymmetric PSF's halo on one side of focus than on the other (a lean
# of the closed loop's fixed point), and the debiasing averages the moment's extra noise away.
# Synthetic edges (dffd.core.synthetic), fixed point on the aberrated kernel −0.0067 h at 3
# spreads, −0.0006 at 3.5, +0.0012 at 4 (Gaussian, disc: within ±0.0006); the reference optics'
# paper-circle (seeds 1–3, simulator's table) LPV ss RMS 8.1 / 7.7 / 9.1 mm at 3 / 3.5 / 4.
# Chosen on those; reported on the simulator's aberrated optics (docs/estimation.md §13).
DEBIAS_WINDOW_SIGMAS = 3.5


class _Moments(Protocol):
    @property
    def cost(self) -> tuple[float, float] | None:
        """(g, σ_g) of the pooled edge moments, or None."""
        ...


class FrameFocus(Protocol):
    """What a focus cost reads from a boundary observation (``contour.BoundaryObservation``)."""

    @property
    def peak_sq(self) -> npt.NDArray[np.float64]:
        """Per-normal max ||∇I||² (NaN where no edge)."""
        ...

    def edge_moments(self, window_sigmas: float | None = None) -> _Moments | None:
        """The pooled edge second moments of the frame (computed on each call)."""
        ...


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


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__, and a burst is fitted up to three times (motion compensation).
@dataclass(slots=True)
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
    out = np.empty(2)
    values = np.ascontiguousarray(peak_sq, dtype=np.float64)
    if not kernel_dispatch.current().focus_cost(values, trim_fraction, out):
        return None
    return float(out[0]), float(out[1])


def edge_variance_cost(
    edge_var: npt.NDArray[np.float64] | None,
    edge_mass: npt.NDArray[np.float64] | None,
    trim_fraction: float = 0.1,
) -> tuple[float, float] | None:
    """Focus cost from the per-normal edge second moments (px²): (g, σ_g) or None.

    ``g`` is the mass-weighted mean of the per-normal moments after dropping ``trim_fraction``
    of the normals at each end of their sorted moments (occlusions, clutter); σ_g the standard
    error of that weighted mean. Blur variances add, so for any PSF ``g = σ0² + c (v0 − v)²``.
    """
    if edge_var is None or edge_mass is None:
        return None
    ok = np.isfinite(edge_var) & np.isfinite(edge_mass)
    var, mass = edge_var[ok], edge_mass[ok]
    n = len(var)
    if n < 8:
        return None
    order = np.argsort(var, kind="stable")
    cut = int(trim_fraction * n)
    keep = order[cut : n - cut] if n - 2 * cut >= 4 else order
    v, w = var[keep], mass[keep]
    total = float(np.add.reduce(w))
    if total <= 0:
        return None
    g = float(np.add.reduce(w * v)) / total
    k = len(v)
    dev = (v - g) * w
    se = math.sqrt(float(np.add.reduce(dev * dev)) * k / (k - 1)) / total
    return g, se


def frame_cost(
    obs: FrameFocus,
    measure: FocusMeasure,
    trim_fraction: float = 0.1,
) -> tuple[float, float] | None:
    """Focus cost (g, σ_g) of one tracked frame with the chosen measure, or None.

    The measure has no default here: the configuration's (``[estimator] focus_measure``) is the
    one default, and every caller passes it.

    ``edge_variance``: the edge moments pooled with the tracker's own ``trim_fraction`` (same
    pooling as :func:`edge_variance_cost`, in its compiled kernel); ``debiased_peak``: the same
    moments on the wider window the peak gradient is debiased against (DEBIAS_WINDOW_SIGMAS);
    ``peak_gradient``: (2).
    """
    if measure == "peak_gradient":
        return focus_cost(obs.peak_sq, trim_fraction)
    window = DEBIAS_WINDOW_SIGMAS if measure == "debiased_peak" else None
    moments = obs.edge_moments(window)
    return None if moments is None else moments.cost


def fit_burst(
    v_mm: Sequence[float],
    g: Sequence[float],
    sigma_g: Sequence[float],
    lens: Lens,
    config: FitConfig | None = None,
    *,
    response: VertexResponse | None = None,
) -> BurstFit:
    """Fit the cost parabola to a burst; closed form for three settings, WLS for more.

    ``response``: the calibration's measured vertex response (``Lens.vertex_response``, for
    the measure of ``g``); where it applies to the bracket the fitted offset from the bracket's
    centre is mapped to the true one (docs/estimation.md §21). Its σ stays the fitted one:
    scaled by the inverse response's slope (< 1 near the centre) it claimed a precision the
    filtered errors did not have (2σ coverage below 0.90 in four of twelve groups on the
    reference optics, §28-29). None: the parabola's vertex as fitted.
    """
    cfg = config if config is not None else FitConfig()
    # A burst has three settings: the parabola through them in closed form on plain floats
    # (NumPy's per-call overhead — lstsq, inv, unique: ~50 µs a fit, three fits a burst —
    # dwarfs the arithmetic). More settings: weighted least squares.
    if len(v_mm) == 3 and len(g) == 3 and len(sigma_g) == 3:
        fitted = _fit3(v_mm, g, sigma_g)
    else:
        fitted = _fit_wls(v_mm, g, sigma_g)
    if fitted is None:
        return _rejected("fewer than three distinct focus settings")
    mid, h, a2, a1, a0, chi, dof, c00, c01, c11 = fitted
    alpha = a2 / (h * h)
    if a2 <= 0:
        return _rejected("alpha <= 0: the cost has no minimum in the bracket", alpha=alpha)
    xv = -a1 / (2 * a2)
    g0, g1 = a1 / (2 * a2 * a2), -1 / (2 * a2)  # ∂xv/∂(a2, a1)
    sigma_x = math.sqrt(max(g0 * g0 * c00 + 2.0 * g0 * g1 * c01 + g1 * g1 * c11, 0.0))
    if response is not None and response.applies(h, mid):
        xv, _slope = response.correct(xv)
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


class _Fitted(NamedTuple):
    """Parabola a2 x² + a1 x + a0 in x = (v − mid)/h; cov(a2, a1) = [[c00, c01], [c01, c11]]."""

    mid: float
    h: float
    a2: float
    a1: float
    a0: float
    chi: float
    dof: int
    c00: float
    c01: float
    c11: float


def _fit3(v_mm: Sequence[float], g: Sequence[float], sigma_g: Sequence[float]) -> _Fitted | None:
    """Parabola through three settings (Lagrange form) and its coefficient covariance."""
    v0, v1, v2 = float(v_mm[0]), float(v_mm[1]), float(v_mm[2])
    y0, y1, y2 = float(g[0]), float(g[1]), float(g[2])
    floor = 1e-12 * max(1.0, abs(y0), abs(y1), abs(y2))
    s0, s1, s2 = (max(float(a), floor) for a in sigma_g)
    if len({_round9(v0), _round9(v1), _round9(v2)}) < 3:
        return None
    lo, hi = min(v0, v1, v2), max(v0, v1, v2)
    mid, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    x0, x1, x2 = (v0 - mid) / h, (v1 - mid) / h, (v2 - mid) / h
    # rows of the inverse of the design [x², x, 1]: c = B y
    d0, d1, d2 = (x0 - x1) * (x0 - x2), (x1 - x0) * (x1 - x2), (x2 - x0) * (x2 - x1)
    b00, b01, b02 = 1.0 / d0, 1.0 / d1, 1.0 / d2
    b10, b11, b12 = -(x1 + x2) / d0, -(x0 + x2) / d1, -(x0 + x1) / d2
    a2 = b00 * y0 + b01 * y1 + b02 * y2
    a1 = b10 * y0 + b11 * y1 + b12 * y2
    a0 = x1 * x2 / d0 * y0 + x0 * x2 / d1 * y1 + x0 * x1 / d2 * y2
    q0, q1, q2 = s0 * s0, s1 * s1, s2 * s2
    c00 = b00 * b00 * q0 + b01 * b01 * q1 + b02 * b02 * q2
    c01 = b00 * b10 * q0 + b01 * b11 * q1 + b02 * b12 * q2
    c11 = b10 * b10 * q0 + b11 * b11 * q1 + b12 * b12 * q2
    return _Fitted(mid, h, a2, a1, a0, 0.0, 0, c00, c01, c11)


def _fit_wls(v_mm: Sequence[float], g: Sequence[float], sigma_g: Sequence[float]) -> _Fitted | None:
    """Weighted least squares of (x², x, 1) for more than three settings."""
    v = np.asarray(v_mm, dtype=np.float64)
    y = np.asarray(g, dtype=np.float64)
    s = np.maximum(np.asarray(sigma_g, dtype=np.float64), 1e-12 * np.abs(y).max(initial=1.0))
    if len(np.unique(np.round(v, 9))) < 3:
        return None
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
    c00, c01, c11 = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    return _Fitted(mid, h, a2, a1, a0, chi, dof, c00, c01, c11)


def _round9(x: float) -> float:
    """``np.round(x, 9)`` on a float (NaN/inf pass through)."""
    return round(x * 1e9) / 1e9 if math.isfinite(x) else x


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
