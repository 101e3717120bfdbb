"""Measurement noise and time offset adapted online (docs/estimation.md §9).

Three small estimators, each a statistic of the Kalman filter's innovations ``ν = y − ẑ⁻`` at
the accepted bursts and of their predicted variance ``S``:

* :class:`InnovationScale` — the ratio ``λ`` of the true measurement variance to the one the
  burst fit states (its delta-method σ, the prior: ``λ = 1``), by innovation-covariance
  matching (Sage–Husa): ``λ ← λ (1 − d + d ν²/S)`` with ``d = 1/(n0 + k)`` (a running mean
  from a prior worth ``n0`` innovations) that becomes an exponential window of ``W`` bursts;
  bounded, and each ``ν²/S`` clipped so that one gross first measurement cannot blow it up.
  Its degrees of freedom (``n0`` + the innovations seen, up to ``W``) give the Student-t
  inflation :func:`student_factor` of every published σ: with a variance estimated from ``n``
  innovations the 2σ interval must widen by ``t_n/z`` — ×6.4 after one, ×1.3 after five, ×1.05
  after thirty — so the first estimates carry a σ that covers their error without a tuned count.
* :class:`TimeOffset` — the lean ``τ`` of a depth measurement (``z_m = z(t_b + τ)``, ``t_b`` the
  mean exposure mid-time of its frames) by recursive least squares on the size invariant
  (``ln(z_m s(t_b)) = ln R − τ ρ``), from the prior ``τ = 0`` that the exposure timing gives;
  bounded. (A regression of the innovations on ż would also pick up the filter's own lag.)
* :func:`shared_frame_correlation` — consecutive rolling bursts share an end frame, so their
  errors are correlated: the vertex of a three-point fit is, to first order, the difference of
  the two end costs over the curvature, so one shared end gives a correlation of ½.

Pure and deterministic; no clock.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from dffd.core import kernel_dispatch

ProcessNoise = Literal["data", "drift", "kf"]

# The burst's parabola is a model of the cost: its vertex moves by ``slope × `` the true offset
# of the sharp setting from the bracket centre, so a vertex far from the centre carries a model
# error ``|1 − slope| × offset`` that no cost noise shows. Slopes measured on the reference
# optics only (docs/estimation.md §8: 0.925 for the peak gradient, 1.005–1.014 for the edge
# second moment; the aberrated optics gave 0.92 / 0.98–1.0, not used).
# "debiased_peak" fits the peak gradient's slope against the edge moment's (dffd.core.combine).
MODEL_SLOPE_ERROR = {"peak_gradient": 0.075, "edge_variance": 0.014, "debiased_peak": 0.014}
# Two-sided 2σ probability of a Gaussian (the coverage an honest σ gives).
_TWO_SIGMA_P = 0.5 * (1.0 + math.erf(2.0 / math.sqrt(2.0)))  # 0.97725
# Above this many degrees of freedom the Student-t factor is ~1 (1.0009 at 1000).
_MAX_DOF = 1000
# Newton steps of t_quantile: from t = 2 it converges in 5-12 for dof 1-1000; the bound only
# keeps a bad argument from looping.
_T_QUANTILE_ITERATIONS = 60


@dataclass(frozen=True, slots=True)
class NoiseAdaptConfig:
    """Parameters of the online noise and time-offset estimates (docs/estimation.md §9)."""

    # The fit's own σ counts as this many innovations (the prior λ = 1): one, so the first
    # published estimates carry the Student-t factor of one degree of freedom.
    prior_innovations: float = 1.0
    # Memory of λ in accepted bursts once the running mean has seen that many (~27 s at the
    # rolling bracket's 2.2 Hz): long enough for a variance estimate within ±20 % (√(2/60)),
    # short enough to follow a depth change of the noise the fit's σ does not model.
    window_bursts: float = 60.0
    scale_min: float = 0.25  # σ no smaller than ½ of the fit's own σ
    scale_max: float = 1.0e4  # σ at most 100× the fit's σ
    # One innovation moves λ by at most this factor's worth (ν²/S clipped): a gross first
    # burst (full-range bracket) must not pin λ high for a minute.
    innovation_clip: float = 25.0
    # Time offset: prior σ of τ (a few frame periods) and the bound of τ̂.
    tau_prior_sigma_s: float = 0.05
    tau_max_s: float = 0.1
    # Off by default: on the held-out (aberrated) optics the regression took a depth-dependent
    # size bias for a lean and pinned τ̂ at −0.1 s (approach), and on the reference optics it
    # stayed within ±0.02 s of the exposure timing's 0 (docs/estimation.md §9).
    adapt_time_offset: bool = False
    # Slow measurement errors (SlowErrors): autocovariance lags of the long-run variance (~5 s of
    # rolling bursts, the scale the filters average over) and the bound of the factor.
    slow_error_lags: int = 10
    slow_error_max: float = 25.0
    # Process noise of the σ propagation (DriftRate): lags of the size invariant's variogram
    # (2 .. this many bursts, ~9 s: the slow filters' time constant) and the bursts it needs.
    drift_max_lag: int = 20
    drift_min_bursts: int = 30
    # The σ propagation's process noise: the Kalman filter's σ_ρ, σ_b until drift_min_bursts size
    # measurements, then "data": none (the size invariant's wander is a slow measurement error,
    # which ι counts; docs/estimation.md §19), "drift": DriftRate's q̂ (§14, §17; it counted that
    # wander a second time); "kf": the Kalman filter's throughout (before §14). The Kalman filter
    # itself keeps its own noise either way.
    process_noise: ProcessNoise = "data"
    # ι's lower bound: two-sided since docs/estimation.md §17 (errors that alternate in sign
    # average out faster than the MA(1) model says: static targets on the reference optics, lags
    # 2-5 correlated −0.1 … −0.4); bounded as λ is (σ no smaller than ½ of the model's). The
    # estimate is corrected for its bias (SlowErrors), without which a two-sided ι
    # made the σ overconfident on white bursts (NEES 1.24; docs/estimation.md §17, §23).
    slow_error_min: float = 0.25
    # ι acts from this many bursts on (33 before docs/estimation.md §19), its lags a third of
    # the bursts seen (at most slow_error_lags): 12 bursts give 3 lags, which see the shared
    # frame's lag-1 correlation and the closed loop's negative ones at lags 2-3 (from 9
    # bursts, 2 lags, the mean-removal correction 1/(1 − M/n) is already 1.5)
    slow_error_min_bursts: int = 12


def student_factor(dof: float) -> float:
    """Factor that widens a Gaussian 2σ interval to a Student-t one with ``dof`` degrees of
    freedom (a variance estimated from ``dof`` samples): t⁻¹(0.977; dof) / Φ⁻¹(0.977)."""
    return _student_factor(max(1, min(round(dof), _MAX_DOF)))


def model_sigma_v_mm(v_mm: tuple[float, ...], v_hat_mm: float, measure: str) -> float:
    """σ of the vertex (mm of v) from the parabola model's error at its offset in the bracket."""
    if not v_mm or not math.isfinite(v_hat_mm):
        return 0.0
    mid = 0.5 * (min(v_mm) + max(v_mm))
    return MODEL_SLOPE_ERROR.get(measure, max(MODEL_SLOPE_ERROR.values())) * abs(v_hat_mm - mid)


def shared_frame_correlation(previous: tuple[int, ...], current: tuple[int, ...]) -> float:
    """Correlation of two bursts' depth errors from the frames they share (0, ½ or more)."""
    if not previous or not current:
        return 0.0
    shared = len(set(previous) & set(current))
    # the vertex ≈ (g₋ − g₊)/curvature: each end frame carries half of the noise variance
    return min(0.5 * shared, 0.9)


class InnovationScale:
    """Ratio λ of the true measurement variance to the fit's stated one, from ν²/S."""

    def __init__(self, config: NoiseAdaptConfig) -> None:
        self.config = config
        self.scale = 1.0
        self.count = 0  # innovations seen

    @property
    def dof(self) -> float:
        """Degrees of freedom of the estimate: the prior's plus the innovations (≤ window)."""
        c = self.config
        return min(c.prior_innovations + self.count, c.window_bursts)

    @property
    def factor(self) -> float:
        """Student-t inflation of a σ that rests on this estimate."""
        return student_factor(self.dof)

    def update(self, innovation: float, s: float) -> float:
        """Fold in one innovation with predicted variance ``s`` (computed with the current λ)."""
        c = self.config
        if not (s > 0 and math.isfinite(innovation)):
            return self.scale
        q = min(innovation * innovation / s, c.innovation_clip)
        self.count += 1
        d = 1.0 / min(c.prior_innovations + self.count, c.window_bursts)
        scale = self.scale * (1.0 - d + d * q)
        self.scale = min(max(scale, c.scale_min), c.scale_max)
        return self.scale


class SlowErrors:
    """How much slower than modelled the measurement errors decorrelate: a filter's average of
    N measurements has a variance the long-run variance of their errors sets, not γ₀/N.

    The size measurements ``x_k = ln(z_m s(t_b))`` equal ``ln R`` plus measurement error whatever
    the target does (the size invariant), so their normalised residuals about the window's
    weighted mean, ``r_k = (x_k − m)/σ_k``, sample the errors' autocovariance γ_j. The ratio of the
    long-run variance (Bartlett weights up to ``lags``) to the one the filters assume (MA(1) with
    the shared-frame correlation ``c``) is the factor by which every filtered variance is
    underestimated (``ι > 1``) or overestimated (``ι < 1``): ``ι = LRV / (γ₀ (1 + 2c w₁))``.

    The Bartlett estimate of a long-run variance with ``M = lags + 1`` over ``n`` samples about
    their mean is biased low by ~``M/n`` (the mean removed); the factor is ``ι̂ / (1 − M/n)``,
    which makes E[ι̂] ≈ 1 on white and MA(1) errors (docs/estimation.md §23; §19's
    ``ι̂ (1 + r)/(1 − r/2)``, ``r = 4M/3n``, made E[1/ι̂] ≈ 1 and E[ι̂] 1.2–1.4, to make up for a
    propagated variance that was too small after the hand-over). The lags grow with the bursts
    seen (``n/3 − 1``, at most ``lags``), so ι acts from ``slow_error_min_bursts`` on (§19);
    bounded to ``[slow_error_min, slow_error_max]``.
    """

    def __init__(self, config: NoiseAdaptConfig) -> None:
        self.config = config
        # the window, oldest first: ln sizes and relative σ (the arrays the kernel reads)
        size = int(config.window_bursts)
        self._log_size = np.empty(size)
        self._sigma = np.empty(size)
        self._n = 0
        self._gamma = np.empty(config.slow_error_lags + 1)
        self.factor = 1.0

    def update(self, log_size: float, sigma_rel: float, corr: float) -> float:
        """One size measurement (ln, relative σ) and the modelled lag-1 correlation; returns ι."""
        c = self.config
        if not (sigma_rel > 0 and math.isfinite(log_size)):
            return self.factor
        x, sig = self._log_size, self._sigma
        if self._n == len(x):  # the window is full: the oldest burst leaves
            x[:-1] = x[1:]
            sig[:-1] = sig[1:]
        else:
            self._n += 1
        n = self._n
        x[n - 1] = log_size
        sig[n - 1] = sigma_rel
        # the lags grow with the window (a third of it, at most ``slow_error_lags``): the
        # debiased estimate below is as honest at 12 bursts and 3 lags as at 60 and 10
        lags = min(c.slow_error_lags, n // 3 - 1)
        if n < c.slow_error_min_bursts or lags < 1:
            return self.factor
        # γ_j = Σ_k r_k r_{k−j} / n of the residuals r = (x − m)/σ about the 1/σ²-weighted
        # mean, j = 0 … lags: one kernel call (Python's sums over 60 bursts × 11 lags cost
        # ~50 µs a burst in the core's loop)
        kernel_dispatch.current().slow_error_gammas(x[:n], sig[:n], lags, self._gamma)
        gamma = self._gamma[: lags + 1].tolist()
        if gamma[0] <= 0:
            return self.factor
        lrv = gamma[0] + 2.0 * sum((1.0 - j / (lags + 1)) * gamma[j] for j in range(1, lags + 1))
        model = gamma[0] * (1.0 + 2.0 * corr * (1.0 - 1.0 / (lags + 1)))
        # residuals about the window's own mean: each γ̂_j is low by ~LRV/n, the Bartlett sum
        # by ~LRV M/n (M = lags + 1), so E[ι̂] ≈ ι after dividing by 1 − M/n. §19's larger
        # factor (1 + r)/(1 − r/2), r = 4M/3n, made E[1/ι̂] ≈ 1 instead; it was needed only
        # because the propagated variance was 1.3-1.5x too small after the hand-over on the
        # synthetic bursts it was checked on (docs/estimation.md §23)
        unbias = 1.0 / (1.0 - (lags + 1) / n)
        self.factor = min(max(unbias * lrv / model, c.slow_error_min), c.slow_error_max)
        return self.factor


class DriftRate:
    """Random-walk rate ``q`` (1/s) of the size invariant ``ln(z s)``: the process noise of every
    estimator's error, estimated from the data.

    On a rigid target ``x_k = ln(z_m s(t_b))`` is ``ln R`` plus the measurement's error whatever
    the target does; anything that makes the model ``ż = −ρ z (+ b)`` drift from the truth (a
    size bias that changes with depth or blur, a non-rigid target, a disturbance ``b``) makes
    ``ln R`` wander, and a wander of ``ln R`` at rate ``q`` is a depth random walk of variance
    ``q z² dt``. Over the window, pairs of size measurements ``j`` bursts apart (``j ≥ 2``: no
    shared frame) give ``E[(x_k − x_{k−j})²] = λ (σ_k² + σ_{k−j}²) + q (t_k − t_{k−j})``; least
    squares on both coefficients (so neither the stated σ's scale nor λ enters) gives ``q̂``,
    clipped at 0. Until ``drift_min_bursts`` have been seen ``q̂`` is None.
    """

    def __init__(self, config: NoiseAdaptConfig) -> None:
        self.config = config
        self._x: deque[tuple[float, float, float]] = deque(maxlen=int(config.window_bursts))
        self.rate: float | None = None

    def update(self, t: float, log_size: float, sigma_rel: float) -> float | None:
        """One size measurement at time ``t`` (s): ln and relative σ; returns ``q̂`` (1/s)."""
        c = self.config
        if not (sigma_rel > 0 and math.isfinite(log_size) and math.isfinite(t)):
            return self.rate
        self._x.append((t, log_size, sigma_rel * sigma_rel))
        n = len(self._x)
        if n < c.drift_min_bursts:
            return self.rate
        # normal equations of d² = λ v + q Δt over the pairs (sums on floats: n·J ≈ 1200 terms)
        svv = svt = stt = svd = std = 0.0
        xs = list(self._x)
        for k in range(2, n):
            tk, xk, vk = xs[k]
            for j in range(2, min(c.drift_max_lag, k) + 1):
                tj, xj, vj = xs[k - j]
                d2 = (xk - xj) ** 2
                v, dt = vk + vj, tk - tj
                svv += v * v
                svt += v * dt
                stt += dt * dt
                svd += v * d2
                std += dt * d2
        det = svv * stt - svt * svt
        if not det > 0:
            return self.rate
        self.rate = max((svv * std - svt * svd) / det, 0.0)
        return self.rate


class TimeOffset:
    """τ̂ of ``z_m = z(t_b + τ)`` by recursive least squares on the size invariant.

    Under ``z s = R`` a measurement gives ``ln(z_m s(t_b)) = ln R − τ ρ(t_b)`` to first order
    (``ρ = ṡ/s``): regressing those on ``[1, −ρ]`` over the bursts estimates ``τ`` free of any
    filter's lag (R is a constant: no dynamics enter). Prior ``τ = 0`` (the exposure timing),
    a diffuse ``ln R``; without motion there is no information and τ̂ stays at the prior.
    """

    def __init__(self, config: NoiseAdaptConfig) -> None:
        self.config = config
        self._theta = (0.0, 0.0)  # ln R, τ
        # covariance of (ln R, τ): diffuse size, the prior σ of τ
        self._p = (1.0e6, 0.0, 0.0, config.tau_prior_sigma_s**2)
        self._started = False

    @property
    def tau_s(self) -> float:
        """τ̂ (s), bounded by ``tau_max_s``; 0 when not adapting."""
        if not self.config.adapt_time_offset:
            return 0.0
        return min(max(self._theta[1], -self.config.tau_max_s), self.config.tau_max_s)

    @property
    def sigma_s(self) -> float:
        """Standard deviation of τ̂."""
        return math.sqrt(self._p[3])

    def update(self, log_size: float, rho: float, var: float) -> float:
        """One burst: ``log_size = ln(z_m s(t_b))``, the size rate ``rho`` at ``t_b`` (1/s) and
        the variance of ``log_size`` (the measurement's relative variance); returns τ̂."""
        if not (var > 0 and math.isfinite(log_size) and math.isfinite(rho)):
            return self.tau_s
        if not self._started:
            self._theta = (log_size, self._theta[1])
            self._started = True
        h0, h1 = 1.0, -rho
        p00, p01, p10, p11 = self._p
        ph0, ph1 = p00 * h0 + p01 * h1, p10 * h0 + p11 * h1  # P h
        s = h0 * ph0 + h1 * ph1 + var
        k0, k1 = ph0 / s, ph1 / s
        resid = log_size - (self._theta[0] * h0 + self._theta[1] * h1)
        self._theta = (self._theta[0] + k0 * resid, self._theta[1] + k1 * resid)
        # P ← P − K (P h)ᵀ
        self._p = (p00 - k0 * ph0, p01 - k0 * ph1, p10 - k1 * ph0, p11 - k1 * ph1)
        return self.tau_s


@functools.lru_cache(maxsize=_MAX_DOF)
def _student_factor(dof: int) -> float:
    # Φ⁻¹(_TWO_SIGMA_P) is 2 by definition.
    return t_quantile(_TWO_SIGMA_P, dof) / 2.0


def t_quantile(p: float, dof: int) -> float:
    """Student-t quantile ``t⁻¹(p; dof)`` for ``p`` in (0.5, 1) and a whole ``dof`` >= 1.

    Without SciPy (importing scipy.stats cost a start ~0.35 s of CPU): Newton's method on the
    closed-form two-sided probability of whole degrees of freedom (Abramowitz & Stegun 26.7.3-4);
    within 1e-13 of ``scipy.stats.t.ppf`` for dof 1-1000 (tests/test_core_noise.py).
    """
    q = 2.0 * p - 1.0
    log_norm = math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2) - 0.5 * math.log(dof * math.pi)
    t = 2.0
    for _ in range(_T_QUANTILE_ITERATIONS):
        density = math.exp(log_norm - (dof + 1) / 2 * math.log1p(t * t / dof))
        step = (_t_two_sided(t, dof) - q) / (2.0 * density)
        t -= step
        if abs(step) <= 1e-15 * t:
            break
    return t


def _t_two_sided(t: float, dof: int) -> float:
    """P(|T| <= t) for Student's t with a whole ``dof`` (A&S 26.7.3 odd, 26.7.4 even)."""
    theta = math.atan(t / math.sqrt(dof))
    c2 = math.cos(theta) ** 2
    term = total = 1.0
    if dof % 2:
        if dof == 1:
            return 2.0 * theta / math.pi
        for k in range(1, (dof - 1) // 2):
            term *= c2 * (2 * k) / (2 * k + 1)
            total += term
        return 2.0 / math.pi * (theta + math.sin(theta) * math.cos(theta) * total)
    for k in range(1, dof // 2):
        term *= c2 * (2 * k - 1) / (2 * k)
        total += term
    return math.sin(theta) * total
