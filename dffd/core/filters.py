"""Depth filters and observers (design.md §4): CF1, CF2, the LPV observer, a time-varying Kalman
filter on the exactly discretised LPV model, and a differentiator for ``ṙ``.

All are continuous-time designs discretised *exactly* for inputs held over a step (zero-order
hold): 2×2 matrix exponentials are evaluated in closed form (:func:`expm2`), so a step costs a few
microseconds and is exact for any step length. Stability and the gain design of the LPV observer
are derived in ``docs/estimation.md``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

_SMALL = 1e-9
# Memoised exp(M dt): on every frame with an estimate the three axes of each velocity estimator
# and CF2's two inputs step with the same (M, dt), so most evaluations repeat one just made; a few
# entries do.
_EXPM_CACHE = 16


Mat2 = tuple[float, float, float, float]  # row-major 2×2
Vec2 = tuple[float, float]


def expm2(a: FloatArray) -> FloatArray:
    """exp(A) of a real 2×2 matrix in closed form (Cayley–Hamilton)."""
    return np.array(_expm2(_mat(a))).reshape(2, 2)


def zoh2(m: FloatArray, u: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """For ``x' = M x + u`` with constant ``u`` over ``dt``: (exp(M dt), ∫exp(Mτ)dτ · u)."""
    phi, gam = _zoh2(_mat(m), (float(u[0]), float(u[1])), dt)
    return np.array(phi).reshape(2, 2), np.array(gam)


def exp_input2(
    m: FloatArray, u0: FloatArray, lam: float, dt: float
) -> tuple[FloatArray, FloatArray]:
    """For ``x' = M x + u0 e^{λτ}`` over ``dt``: (exp(M dt), ∫exp(M(dt−τ)) u0 e^{λτ} dτ).

    The measurement transported by the size invariant, ``y(τ) = R_m / s(τ)``, is exactly such an
    exponential between frames (``s`` grows as ``e^{ρτ}``), so this is the exact discretisation.
    """
    phi, gam = _exp_input2(_mat(m), (float(u0[0]), float(u0[1])), lam, dt)
    return np.array(phi).reshape(2, 2), np.array(gam)


def exp_input2_floats(m: Mat2, u0: Vec2, lam: float, dt: float) -> tuple[Mat2, Vec2]:
    """:func:`exp_input2` on row-major float tuples (no arrays: for per-frame callers)."""
    return _exp_input2(m, u0, lam, dt)


def expm2_floats(a: Mat2) -> Mat2:
    """:func:`expm2` on a row-major float tuple (memoised; for per-frame callers)."""
    return _expm2(a)


def cf2_gains(sigma_psi: float, sigma_beta: float, sigma_z: float) -> tuple[float, float]:
    """Lemma 1: CF2 gains equal to the stationary Kalman gains of model (11)."""
    k1 = math.sqrt(2.0 * sigma_beta / sigma_z + (sigma_psi / sigma_z) ** 2)
    k2 = sigma_beta / sigma_z
    return k1, k2


class Differentiator:
    """Second-order state-variable filter: ``ṙ`` ≈ s ω²/(s² + 2ζωs + ω²) r.

    Unit DC gain on ``r`` and a derivative that rolls off above ω, so pixel noise on ``r`` is not
    amplified without bound (what a finite difference would do).
    """

    def __init__(self, omega: float, zeta: float = 1 / math.sqrt(2)) -> None:
        if omega <= 0:
            raise ValueError("differentiator bandwidth must be > 0")
        self._m: Mat2 = (0.0, 1.0, -omega * omega, -2.0 * zeta * omega)
        self._b = omega * omega
        self._x: Vec2 | None = None

    def reset(self, value: float) -> None:
        """Start at rest at ``value``."""
        self._x = (float(value), 0.0)

    def update(self, value: float, dt: float) -> tuple[float, float]:
        """Feed a new sample held over the last ``dt``; return (filtered value, derivative)."""
        if self._x is None:
            self.reset(value)
            return value, 0.0
        if dt > 0:
            phi, gam = _zoh2(self._m, (0.0, self._b * value), dt)
            x0, x1 = self._x
            self._x = (
                phi[0] * x0 + phi[1] * x1 + gam[0],
                phi[2] * x0 + phi[3] * x1 + gam[1],
            )
        return float(self._x[0]), float(self._x[1])


class CF1:
    """First-order complementary filter (8), known target size: ẑ' = ψ_m + k (z_m − ẑ)."""

    def __init__(self, k: float) -> None:
        self.k = k
        self.z: float | None = None

    def reset(self, z: float) -> None:
        """Initialise at ``z``."""
        self.z = z

    def step(self, dt: float, y: float, psi: float, lam: float = 0.0) -> float:
        """Advance by ``dt``: ``ψ_m = psi`` held, ``z_m = y e^{λτ}`` (``y`` at the step start)."""
        if self.z is None:
            self.z = y
        e = math.exp(-self.k * dt)
        if abs(lam + self.k) * dt < 1e-9:
            meas = self.k * y * dt * e
        else:
            meas = self.k * y * (math.exp(lam * dt) - e) / (lam + self.k)
        self.z = e * self.z + (1.0 - e) * psi / self.k + meas
        return self.z


class CF2:
    """Second-order complementary filter with bias estimation (10); ẑ = x̂1, β̂ = x̂2."""

    def __init__(self, k1: float, k2: float) -> None:
        self.k1, self.k2 = k1, k2
        self._f: Mat2 = (-k1, 1.0, -k2, 0.0)
        self._x: Vec2 | None = None  # floats: a 2-vector per frame (see _step2)

    @property
    def x(self) -> FloatArray | None:
        """The state [x̂1, x̂2] (a new array)."""
        return None if self._x is None else np.array(self._x)

    @property
    def z(self) -> float | None:
        """Depth estimate."""
        return None if self._x is None else self._x[0]

    @property
    def beta(self) -> float | None:
        """Estimated bias β of ψ_m (m/s): in steady state x̂2 → −β, so β̂ = −x̂2."""
        return None if self._x is None else -self._x[1]

    def reset(self, z: float, beta: float = 0.0) -> None:
        """Initialise the state (``beta`` is the bias of ψ_m)."""
        self._x = (float(z), -float(beta))

    def step(self, dt: float, y: float, psi: float, lam: float = 0.0) -> float:
        """Advance by ``dt``: ``ψ_m = psi`` held, ``z_m = y e^{λτ}`` (``y`` at the step start)."""
        if self._x is None:
            self.reset(y)
            assert self._x is not None
        phi, gam_y = _exp_input2(self._f, (self.k1 * y, self.k2 * y), lam, dt)
        _, gam_psi = _zoh2(self._f, (psi, 0.0), dt)
        self._x = _step2(phi, self._x, (gam_y[0] + gam_psi[0], gam_y[1] + gam_psi[1]))
        return self._x[0]

    def transfer(self, s: complex) -> tuple[complex, complex, complex]:
        """(T1, T2, Fψ) at Laplace variable ``s``: ẑ = T1 z_m + Fψ ψ_m and T2 = Fψ · s."""
        den = s * s + self.k1 * s + self.k2
        return (self.k1 * s + self.k2) / den, s * s / den, s / den


@dataclass(frozen=True, slots=True)
class LPVGains:
    """Gain schedule of the LPV observer: k1(ρ) = k1⁰ − sat(ρ), k2 constant."""

    k1_0: float
    k2: float
    rho_min: float
    rho_max: float

    @property
    def decay_rate(self) -> float:
        """Designed exponential decay rate of the estimation error: −max Re λ(F0)."""
        disc = self.k1_0**2 - 4 * self.k2
        if disc >= 0:
            return 0.5 * (self.k1_0 - math.sqrt(disc))
        return 0.5 * self.k1_0

    @classmethod
    def from_poles(cls, omega: float, zeta: float, rho_min: float, rho_max: float) -> LPVGains:
        """Error dynamics with natural frequency ``omega`` and damping ``zeta``."""
        return cls(2 * zeta * omega, omega * omega, rho_min, rho_max)


class LPVObserver:
    """Observer for ``ż = −ρ z + b``, ``ḃ = 0``, ``y = z_m`` with ρ = ṙ/r measured (no size R).

    ``x̂' = A(ρ) x̂ + K(ρ)(y − ẑ)``, ``A(ρ) = [[−ρ, 1], [0, 0]]``, ``K(ρ) = [k1⁰ − sat(ρ), k2]``.
    For ρ inside ``[rho_min, rho_max]`` the error matrix ``A − K C = [[−k1⁰, 1], [−k2, 0]]`` is
    constant and Hurwitz, so the error decays at ``gains.decay_rate`` for *every* ρ(t) there.
    """

    def __init__(self, gains: LPVGains) -> None:
        if gains.k1_0 <= 0 or gains.k2 <= 0 or gains.rho_min >= gains.rho_max:
            raise ValueError("LPV gains need k1_0 > 0, k2 > 0 and rho_min < rho_max")
        self.gains = gains
        self._x: Vec2 | None = None  # floats: a 2-vector per frame (see _step2)

    @property
    def x(self) -> FloatArray | None:
        """The state [ẑ, b̂] (a new array)."""
        return None if self._x is None else np.array(self._x)

    @property
    def z(self) -> float | None:
        """Depth estimate."""
        return None if self._x is None else self._x[0]

    @property
    def b(self) -> float | None:
        """Estimated additive disturbance on ż (m/s)."""
        return None if self._x is None else self._x[1]

    def reset(self, z: float, b: float = 0.0) -> None:
        """Initialise the state."""
        self._x = (float(z), float(b))

    def closed_loop(self, rho: float) -> tuple[FloatArray, FloatArray]:
        """(A(ρ) − K(ρ)C, K(ρ)): error matrix and gain at ``rho``."""
        g = self.gains
        k1 = g.k1_0 - min(max(rho, g.rho_min), g.rho_max)
        m = np.array([[-rho - k1, 1.0], [-g.k2, 0.0]])
        return m, np.array([k1, g.k2])

    def derivative(self, x: FloatArray, rho: float, y: float) -> FloatArray:
        """Continuous-time right-hand side (for tests and numerical integration)."""
        m, k = self.closed_loop(rho)
        return np.asarray(m @ x + k * y, dtype=np.float64)

    def step(self, dt: float, rho: float, y: float, lam: float = 0.0) -> float:
        """Advance by ``dt`` with ρ constant and ``y e^{λτ}`` (``y`` at the step start); exact.

        With the transported measurement ``λ = −ρ``; ``λ = 0`` is a held measurement.
        """
        if self._x is None:
            self.reset(y)
            assert self._x is not None
        g = self.gains
        k1 = g.k1_0 - min(max(rho, g.rho_min), g.rho_max)
        phi, gam = _exp_input2((-rho - k1, 1.0, -g.k2, 0.0), (k1 * y, g.k2 * y), lam, dt)
        self._x = _step2(phi, self._x, gam)
        return self._x[0]


@dataclass(frozen=True, slots=True)
class KFNoise:
    """Noise model of the time-varying Kalman filter."""

    # Measured on the reference simulator (hil run --fast, steady state, z_m error against the
    # truth at the burst's frames, divided by |dz/dv|): frame-to-frame ln(r) error 0.03 % (it
    # telescopes: not a random walk); vertex error of rolling bursts 0.24 µm of v at rest
    # (lag-1 autocorrelation +0.38 from the shared end frames: long-run σ ≈ 0.24·√1.76 ≈ 0.32),
    # 0.35–0.49 µm on the moving scenarios (after the pan/tilt fix; it was 0.9 µm before).
    sigma_rho: float = 0.0002  # 1/s/√Hz: white noise on ρ (size-ratio noise) ⇒ ż noise ∝ z
    sigma_b: float = 0.0005  # m/s/√Hz: random walk of the disturbance b
    # Not used by the pipeline any more: the measurement noise is the fit's σ scaled by a ratio
    # adapted online (dffd/core/noise.py, docs/estimation.md §9); kept for old --set overrides.
    sigma_v_mm: float = 0.0004
    # m/s: the largest initial uncertainty of b. On a rigid target z s = R carries the motion
    # (ż = −ρz exactly) and b is a model error that only motion brings, so b's prior σ is the
    # target's speed |ρ z| at the first update, at most this (DepthKF.open_b): on a static
    # target 0.05 m/s let the first bursts' noise be read as a velocity (docs/estimation.md §24).
    sigma_b0: float = 0.05


@dataclass(frozen=True, slots=True)
class KFTraceEvent:
    """One step of a :class:`DepthKF`: the state and covariance after it (and what made it)."""

    kind: Literal["reset", "predict", "update", "frame"]
    x: FloatArray | None = None
    p: FloatArray | None = None
    phi: FloatArray | None = None  # predict: the transition
    q: FloatArray | None = None  # predict: the process noise added
    y: float | None = None  # update: the measurement
    r: float | None = None  # update: its variance
    frame: int | None = None  # frame: the estimate of this frame index holds the last state


class DepthKF:
    """Kalman filter on ``z_{k+1} = (s_k/s_{k+1}) z_k + g_k b_k``: the exact discretisation.

    ``∫ρ dt = ln(s_{k+1}/s_k)`` (``s`` the normalised image size), so the transition over a frame
    is exactly ``s_k/s_{k+1}`` without differentiating the size; ``g_k = (1 − φ)/ρ̄`` is the
    exact response to a constant ``b``. Measurement noise grows ∝ z² (dz/dv ∝ z²).
    """

    def __init__(self, noise: KFNoise, trace: list[KFTraceEvent] | None = None) -> None:
        self.noise = noise
        # [z, b] and the row-major P on floats (a 2-vector and a 2×2 per frame: NumPy's
        # per-call cost was most of a prediction); ``x`` and ``p`` give them as arrays
        self._x: Vec2 | None = None
        self._p: Mat2 = (0.0, 0.0, 0.0, 0.0)
        # every reset, prediction (with its Φ and Q) and update, for an offline smoother
        # (dffd.core.smoother); None: not recorded (the daemon)
        self.trace = trace

    @property
    def x(self) -> FloatArray | None:
        """The state [z, b] (a new array)."""
        return None if self._x is None else np.array(self._x)

    @property
    def p(self) -> FloatArray:
        """The 2×2 error covariance (a new array)."""
        return np.array(self._p).reshape(2, 2)

    @property
    def z(self) -> float | None:
        """Depth estimate."""
        return None if self._x is None else self._x[0]

    @property
    def b(self) -> float | None:
        """Estimated additive disturbance on ż (m/s), the LPV observer's second state."""
        return None if self._x is None else self._x[1]

    @property
    def sigma(self) -> float | None:
        """Standard deviation of the depth estimate."""
        return None if self._x is None else math.sqrt(max(self._p[0], 0.0))

    def reset(self, z: float, sigma_z: float, sigma_b: float | None = None) -> None:
        """Initialise at ``z`` with uncertainty ``sigma_z`` and b = 0 with σ ``sigma_b``
        (default ``sigma_b0``; 0 to set it later with :meth:`open_b`)."""
        sb = self.noise.sigma_b0 if sigma_b is None else sigma_b
        self._x = (float(z), 0.0)
        self._p = (float(sigma_z**2), 0.0, 0.0, float(sb**2))
        if self.trace is not None:
            self.trace.append(KFTraceEvent("reset", self.x, self.p))

    def open_b(self, speed: float) -> None:
        """Add b's prior: σ = the target's speed ``|speed|`` (m/s), at most ``sigma_b0``.

        The estimator bank resets with b known (σ 0) and opens it at the first update: b is a
        model error of ż = −ρz that only motion brings (on a rigid target z s = R carries the
        motion exactly; a static target's b is 0), and at the reset the size rate is the
        acquisition's (docs/estimation.md §24). Added to b's variance (its walk since the reset
        stays), so P stays positive semi-definite.
        """
        if self._x is None:
            return
        p00, p01, p10, p11 = self._p
        prior = min(abs(speed), self.noise.sigma_b0) ** 2
        self._p = (p00, p01, p10, p11 + prior)
        if self.trace is not None:  # for the smoother: process noise added to b, no motion
            q = np.array([[0.0, 0.0], [0.0, prior]])
            self.trace.append(KFTraceEvent("predict", self.x, self.p, phi=np.eye(2), q=q))

    @staticmethod
    def transition(ratio: float, dt: float) -> FloatArray:
        """Φ for a step where the size grew by ``1/ratio`` (ratio = s_k/s_{k+1})."""
        ratio = max(ratio, 1e-6)
        lam = -math.log(ratio)  # = ∫ρ dt
        g = dt if abs(lam) < 1e-9 else dt * (1.0 - ratio) / lam
        return np.array([[ratio, g], [0.0, 1.0]])

    def predict(self, ratio: float, dt: float) -> None:
        """Propagate over ``dt`` with the size ratio ``s_k/s_{k+1}``."""
        if self._x is None or dt <= 0:
            return
        ratio = max(ratio, 1e-6)
        lam = -math.log(ratio)  # = ∫ρ dt
        g = dt if abs(lam) < 1e-9 else dt * (1.0 - ratio) / lam  # as transition()
        z, b = self._x
        n = self.noise
        qz = (n.sigma_rho * z) ** 2 * dt
        qb = n.sigma_b**2
        p00, p01, p10, p11 = self._p
        # Φ P Φᵀ + Q with Φ = [[ratio, g], [0, 1]], written out (a 2×2 per frame)
        a00, a01 = ratio * p00 + g * p10, ratio * p01 + g * p11
        self._x = (ratio * z + g * b, b)
        self._p = (
            a00 * ratio + a01 * g + qz + qb * dt**3 / 3,
            a01 + qb * dt**2 / 2,
            p10 * ratio + p11 * g + qb * dt**2 / 2,
            p11 + qb * dt,
        )
        if self.trace is not None:
            q = np.array([[qz + qb * dt**3 / 3, qb * dt**2 / 2], [qb * dt**2 / 2, qb * dt]])
            phi = np.array([[ratio, g], [0.0, 1.0]])
            self.trace.append(KFTraceEvent("predict", self.x, self.p, phi=phi, q=q))

    def update(self, y: float, sigma_y: float) -> float:
        """Correct with a depth measurement ``y`` of standard deviation ``sigma_y``; innovation."""
        if self._x is None:
            self.reset(y, sigma_y)
            return 0.0
        x0, x1 = self._x
        p00, p01, p10, p11 = self._p
        r = sigma_y**2
        s = p00 + r
        k0, k1 = p00 / s, p10 / s
        innov = y - x0
        self._x = (x0 + k0 * innov, x1 + k1 * innov)
        # Joseph form keeps P symmetric positive definite: (I − K C) P (I − K C)ᵀ + K R Kᵀ with
        # C = [1, 0], written out on floats (a 2×2 per measurement)
        a00, a01 = (1.0 - k0) * p00, (1.0 - k0) * p01
        a10, a11 = p10 - k1 * p00, p11 - k1 * p01
        self._p = (
            a00 * (1.0 - k0) + k0 * k0 * r,
            a01 - a00 * k1 + k0 * k1 * r,
            a10 * (1.0 - k0) + k1 * k0 * r,
            a11 - a10 * k1 + k1 * k1 * r,
        )
        if self.trace is not None:
            self.trace.append(KFTraceEvent("update", self.x, self.p, y=y, r=r))
        return innov


# -- scalar 2×2 kernels -----------------------------------------------------------------------
# The filters step once per frame with a contour, on 2-vectors: NumPy's per-call overhead on 2×2
# arrays (a few µs per operation, ~0.3 ms per frame in total, measured) dwarfs the arithmetic, so
# the closed forms are evaluated on Python floats.
def _mat(a: FloatArray) -> Mat2:
    return float(a[0, 0]), float(a[0, 1]), float(a[1, 0]), float(a[1, 1])


@functools.lru_cache(maxsize=_EXPM_CACHE)
def _expm2(a: Mat2) -> Mat2:
    a00, a01, a10, a11 = a
    s = 0.5 * (a00 + a11)
    det = a00 * a11 - a01 * a10
    disc = s * s - det
    if disc > _SMALL:
        q = math.sqrt(disc)
        c, sh = math.cosh(q), math.sinh(q) / q
    elif disc < -_SMALL:
        q = math.sqrt(-disc)
        c, sh = math.cos(q), math.sin(q) / q
    else:
        c, sh = 1.0 + 0.5 * disc, 1.0 + disc / 6.0
    e = math.exp(s)
    return (e * (c + sh * (a00 - s)), e * sh * a01, e * sh * a10, e * (c + sh * (a11 - s)))


def _solve2(m: Mat2, det: float, v: Vec2) -> Vec2:
    m00, m01, m10, m11 = m
    return (m11 * v[0] - m01 * v[1]) / det, (m00 * v[1] - m10 * v[0]) / det


def _zoh2(m: Mat2, u: Vec2, dt: float) -> tuple[Mat2, Vec2]:
    m00, m01, m10, m11 = m
    phi = _expm2((m00 * dt, m01 * dt, m10 * dt, m11 * dt))
    det = m00 * m11 - m01 * m10
    if abs(det) > _SMALL:
        p00, p01, p10, p11 = phi
        rhs = ((p00 - 1.0) * u[0] + p01 * u[1], p10 * u[0] + (p11 - 1.0) * u[1])
        return phi, _solve2(m, det, rhs)
    # singular M: integrate with the series of ∫exp(Mτ)dτ (rare; tests only)
    mm = np.array([[m00, m01], [m10, m11]])
    gam = np.zeros((2, 2))
    term = np.eye(2) * dt
    for k in range(1, 30):
        gam = gam + term
        term = term @ mm * dt / (k + 1)
    g = gam @ np.array(u)
    return phi, (float(g[0]), float(g[1]))


def _exp_input2(m: Mat2, u0: Vec2, lam: float, dt: float) -> tuple[Mat2, Vec2]:
    if abs(lam) * dt < 1e-9:
        return _zoh2(m, u0, dt)
    m00, m01, m10, m11 = m
    phi = _expm2((m00 * dt, m01 * dt, m10 * dt, m11 * dt))
    shifted = (m00 - lam, m01, m10, m11 - lam)
    det = shifted[0] * shifted[3] - shifted[1] * shifted[2]
    if abs(det) < _SMALL:  # λ is an eigenvalue of M: fall back to the held mean value
        mean = (math.exp(lam * dt) - 1.0) / (lam * dt)
        return _zoh2(m, (u0[0] * mean, u0[1] * mean), dt)
    el = math.exp(lam * dt)
    p00, p01, p10, p11 = phi
    rhs = ((p00 - el) * u0[0] + p01 * u0[1], p10 * u0[0] + (p11 - el) * u0[1])
    return phi, _solve2(shifted, det, rhs)


def _step2(phi: Mat2, x: Vec2, gam: Vec2) -> Vec2:
    """phi @ x + gam on floats (the fixed-gain filters' states: a new array per frame and the
    float conversions back were most of a step)."""
    x0, x1 = x
    return phi[0] * x0 + phi[1] * x1 + gam[0], phi[2] * x0 + phi[3] * x1 + gam[1]
