"""Error covariance of one linear estimator: its error and the measurement it holds.

Every estimator is linear in its inputs, so its error ``e = x − x̂`` obeys a linear recursion
driven by the process noise and by the error ``ε`` of the measurement it currently holds. The
held measurement is the transported ``y = R_m/s`` of the last accepted burst: between bursts
``ε`` scales with the size ratio exactly as ``y`` does, and at a burst it is replaced by the
new measurement's error, correlated with the old one when the two bursts share a frame.
:class:`ErrorCovariance` carries the covariance of ``[e, ε]`` for one estimator, and
:class:`SharedFrameCovariance` — what is published — that of ``[e, ε, k]`` per unit λ, with the
shared frame as the MA(1) it is (docs/estimation.md §23):

* fixed-gain filters (CF1, CF2, LPV): over a frame ``e ← Φ e − g ε``, ``ε ← φ ε`` with ``Φ``
  the filter's own exact transition and ``g`` its exact response to a unit held ``y``
  (:func:`dffd.core.filters.exp_input2`, the discretisation the filters step with);
* the Kalman filter: ``e ← Φ e`` between bursts and ``e ← (I − K C) e − K ε`` at an update with
  the gain it used — its own P assumes white measurement noise, this one does not.

Pure; written out on floats (four of these step on every frame, and NumPy's per-call cost on
3×3 arrays was most of the cost). :mod:`dffd.core.uncertainty` runs one per estimator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from dffd.core.filters import Mat2, Vec2

FloatArray = npt.NDArray[np.float64]

# The share of a burst's error variance that its end frame carries, and so the most a following
# burst that shares that frame can share (the vertex ≈ the end costs' difference over the
# curvature: each end frame carries half; dffd.core.noise.shared_frame_correlation).
SHARED_END_SHARE = 0.5


class ErrorCovariance:
    """Covariance of ``[e (n states), ε]`` of one linear estimator (``n`` = 1 or 2).

    Kept in three parts that add up with the process-noise intensities as weights: ``p``, driven
    by the measurements' errors and the initial error; ``pz``, the error covariance (``n × n``)
    that a unit random walk of ``ln z`` (variance ``z² dt`` per step) would have caused; ``pb``,
    the one a unit random walk of ``b`` (variance ``dt``) would have caused. Every step is
    linear in the noise, so ``P = p + w_z pz + w_b pb`` for any intensities, and the weights can
    change after the fact: when the data give the process noise (DriftRate), the whole history
    is re-weighted, including what a filter inherited at a hand-over (docs/estimation.md §17).
    """

    def __init__(self, n: int) -> None:
        self.n = n
        # P of [e, ε] as rows of floats: four of these step on every frame, and NumPy's
        # per-call cost on 3×3 arrays was most of the cost (``p`` gives the array)
        self._rows: list[list[float]] = [[0.0] * (n + 1) for _ in range(n + 1)]
        self.pz: list[float] = [0.0] * (n * n)  # row-major n × n
        self.pb: list[float] | None = [0.0] * (n * n)  # None once its weight is 0 for good
        self.weights: tuple[float, float] = (0.0, 0.0)  # (w_z, w_b), set by the owner

    @property
    def p(self) -> FloatArray:
        """The measurement-driven part of the covariance of ``[e, ε]`` (a new array)."""
        return np.array(self._rows)

    @property
    def var_z(self) -> float:
        """Variance of the depth error."""
        wz, wb = self.weights
        v = self._rows[0][0] + wz * self.pz[0]
        if self.pb is not None:
            v += wb * self.pb[0]
        return max(v, 0.0)

    def total(self) -> FloatArray:
        """The whole covariance of ``[e, ε]`` at the current weights."""
        n = self.n
        wz, wb = self.weights
        p = np.array(self._rows)
        p[:n, :n] += wz * np.array(self.pz).reshape(n, n)
        if self.pb is not None:
            p[:n, :n] += wb * np.array(self.pb).reshape(n, n)
        return p

    def error_block(self) -> tuple[float, ...]:
        """The depth error's block (``n × n``, row-major) of :meth:`total`, on floats (the same
        sums: the measurement part, plus each weighted walk in turn)."""
        n = self.n
        wz, wb = self.weights
        rows, pz, pb = self._rows, self.pz, self.pb
        out = []
        for i in range(n):
            for j in range(n):
                v = rows[i][j] + wz * pz[i * n + j]
                if pb is not None:
                    v = v + wb * pb[i * n + j]
                out.append(v)
        return tuple(out)

    def clone(self) -> ErrorCovariance:
        """An independent copy."""
        out = ErrorCovariance(self.n)
        out._rows = [row[:] for row in self._rows]
        out.pz = list(self.pz)
        out.pb = None if self.pb is None else list(self.pb)
        out.weights = self.weights
        return out

    def drop_b_walk(self) -> None:
        """Forget the b random walk's part (its weight is 0 from now on)."""
        self.pb = None

    def propagate(self, phi: Mat2, g: Vec2, ratio: float, qz: Mat2, qb: Mat2) -> None:
        """One frame: ``e ← phi e − g ε + w``, ``ε ← ratio ε``; ``qz`` and ``qb`` are the
        covariances of ``w`` for a unit intensity of each random walk. For ``n = 1`` only the
        first entries of ``phi``, ``g``, ``qz`` and ``qb`` are used.

        Written out on floats: it runs for four estimators on every frame, and NumPy's
        per-call overhead on 3×3 arrays is most of the cost (measured ~4× slower).
        """
        rows = self._rows
        if self.n == 1:
            (a, c), (_, d) = rows
            f, g0 = phi[0], g[0]
            u = f * c - g0 * d
            e = f * f * a - 2.0 * f * c * g0 + d * g0 * g0
            self._rows = [[e, ratio * u], [ratio * u, ratio * ratio * d]]
            self.pz = [f * f * self.pz[0] + qz[0]]
            if self.pb is not None:
                self.pb = [f * f * self.pb[0] + qb[0]]
            return
        (a00, a01, c0), (_, a11, c1), (_, _, d) = rows
        p00, p01, p10, p11 = phi
        g0, g1 = g
        b00, b01 = p00 * a00 + p01 * a01, p00 * a01 + p01 * a11
        b10, b11 = p10 * a00 + p11 * a01, p10 * a01 + p11 * a11
        h0, h1 = p00 * c0 + p01 * c1, p10 * c0 + p11 * c1  # Φ c
        e00 = b00 * p00 + b01 * p01 - 2.0 * h0 * g0 + d * g0 * g0
        e01 = b00 * p10 + b01 * p11 - h0 * g1 - g0 * h1 + d * g0 * g1
        e11 = b10 * p10 + b11 * p11 - 2.0 * h1 * g1 + d * g1 * g1
        u0, u1 = ratio * (h0 - g0 * d), ratio * (h1 - g1 * d)
        self._rows = [[e00, e01, u0], [e01, e11, u1], [u0, u1, ratio * ratio * d]]
        self.pz = _sandwich2(phi, self.pz, qz)
        if self.pb is not None:
            self.pb = _sandwich2(phi, self.pb, qb)

    def replace_measurement(self, var_new: float, corr: float) -> None:
        """The held measurement becomes a new one of variance ``var_new``, correlated ``corr``
        with the old one: ``ε ← c ε + u``, ``c = corr σ_new/σ_old``, var u = (1−corr²) var_new."""
        n = self.n
        rows = self._rows  # in place: no other covariance shares these lists
        var_old = rows[n][n]
        c = corr * math.sqrt(var_new / var_old) if var_old > 0 and corr > 0 else 0.0
        # T P Tᵀ with T = diag(1, …, 1, c): the last row and column scaled by c, the corner by
        # c² (on floats: the same products as the matrix form, whose other terms are zeros)
        for i in range(n):
            rows[i][n] = rows[i][n] * c
            rows[n][i] = c * rows[n][i]
        rows[n][n] = c * rows[n][n] * c + ((1.0 - corr * corr) * var_new if c else var_new)

    def kalman_update(self, k: Sequence[float] | FloatArray) -> None:
        """``e ← (I − K C) e − K ε`` (the held measurement just replaced)."""
        n = self.n
        # T P Tᵀ written out on floats (a few per burst; NumPy's per-call cost on 3×3 arrays was
        # most of the time), T = I with T[:n, 0] −= k and T[:n, n] = −k
        t = [[1.0 if i == j else 0.0 for j in range(n + 1)] for i in range(n + 1)]
        for i, ki in enumerate(k):
            t[i][0] -= float(ki)
            t[i][n] = -float(ki)
        self._rows = _congruence(t, self._rows)
        tn = [row[:n] for row in t[:n]]
        self.pz = _flat(_congruence(tn, _square(self.pz, n)))
        if self.pb is not None:
            self.pb = _flat(_congruence(tn, _square(self.pb, n)))

    def innovation_variance(self) -> float:
        """Variance of the innovation ``ν = y − ẑ = e_z + ε`` (``e = x − x̂``)."""
        n = self.n
        rows = self._rows
        return self.var_z + rows[n][n] + 2.0 * rows[0][n]

    def start(self, var_meas: float, var_second: float) -> None:
        """A filter initialised at a measurement: ``e_z = −ε`` exactly."""
        n = self.n
        p = [[0.0] * (n + 1) for _ in range(n + 1)]
        p[0][0] = p[n][n] = float(var_meas)
        p[0][n] = p[n][0] = -float(var_meas)
        if n == 2:
            p[1][1] = float(var_second)
        self._rows = p
        self.pz = [0.0] * (n * n)
        if self.pb is not None:
            self.pb = [0.0] * (n * n)

    def copy_from(self, other: ErrorCovariance) -> None:
        """Take ``other``'s depth error and measurement block (a seeded filter; others zeroed)."""
        n, m = self.n, other.n
        idx = [0, m] if n == 1 else [0, 1, m]
        rows = other._rows
        self._rows = [[rows[i][j] for j in idx] for i in idx]
        self.pz = [other.pz[0]] if n == 1 else list(other.pz)
        if self.pb is not None:
            src = other.pb if other.pb is not None else [0.0] * (m * m)
            self.pb = [src[0]] if n == 1 else list(src)


class SharedFrameCovariance(ErrorCovariance):
    """Covariance of ``[e (n states), ε, k]`` of one linear estimator, per unit λ: the σ it
    publishes (docs/estimation.md §23).

    Two things differ from :class:`ErrorCovariance` (which the Kalman filter's hand-over rule
    still reads, so no estimate changes):

    * **The shared frame as MA(1).** Consecutive rolling bursts share an end frame, which
      carries half of each one's error variance (:func:`shared_frame_correlation`); a burst's
      error is correlated with the next one's and with no later one. ``ε ← c ε + u`` made it
      AR(1) (correlation ``c^j`` at lag ``j``, long-run variance ``(1+c)/(1−c)`` = 3γ₀ against
      the shared frame's 2γ₀), and a long average of such errors was stated up to 1.5× too
      variable. Here ``k`` is the part of the held measurement's error that the next burst will
      share (variance ½ of it); a new burst's error is ``a k + fresh`` with ``a`` set by the
      correlation of the two, and its own end frame's half becomes the new ``k``.
    * **The measurement part per unit λ.** The filters carry errors of measurements taken
      while λ̂ was still being learned (from its prior 1; the data give 4-5): stated with the
      λ̂ of their time, a start-up error that the LPV inherits at the hand-over and carries for
      tens of seconds was stated up to 2× too small. The measurement part is propagated for
      λ = 1 and scaled by the current λ̂ (``scale``, set by the owner), so the whole history is
      re-weighted when λ̂ changes, as the process noise is (§17).
    """

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self._rows = [[0.0] * (n + 2) for _ in range(n + 2)]
        self.scale = 1.0  # λ̂: the measurement part's weight, set by the owner when λ̂ moves

    @property
    def var_z(self) -> float:
        """Variance of the depth error."""
        wz, wb = self.weights
        v = self.scale * self._rows[0][0] + wz * self.pz[0]
        if self.pb is not None:
            v += wb * self.pb[0]
        return max(v, 0.0)

    def total(self) -> FloatArray:
        """The whole covariance of ``[e, ε, k]`` at the current λ̂ and weights."""
        n = self.n
        wz, wb = self.weights
        p = self.scale * np.array(self._rows)
        p[:n, :n] += wz * np.array(self.pz).reshape(n, n)
        if self.pb is not None:
            p[:n, :n] += wb * np.array(self.pb).reshape(n, n)
        return p

    def error_block(self) -> tuple[float, ...]:
        """The depth error's block (``n × n``, row-major) of :meth:`total`."""
        n = self.n
        t = self.total()
        return tuple(float(t[i, j]) for i in range(n) for j in range(n))

    def clone(self) -> SharedFrameCovariance:
        """An independent copy."""
        out = SharedFrameCovariance(self.n)
        out._rows = [row[:] for row in self._rows]
        out.pz = list(self.pz)
        out.pb = None if self.pb is None else list(self.pb)
        out.weights = self.weights
        out.scale = self.scale
        return out

    def propagate(self, phi: Mat2, g: Vec2, ratio: float, qz: Mat2, qb: Mat2) -> None:
        """One frame: ``e ← phi e − g ε + w``, ``ε ← ratio ε``, ``k ← ratio k`` (both parts of
        the held measurement are transported with it); as :meth:`ErrorCovariance.propagate`."""
        rows = self._rows
        r2 = ratio * ratio
        if self.n == 1:
            (a, c, h), (_, d, f), (_, _, q) = rows
            f0, g0 = phi[0], g[0]
            e = f0 * f0 * a - 2.0 * f0 * c * g0 + d * g0 * g0
            u = ratio * (f0 * c - g0 * d)
            w = ratio * (f0 * h - g0 * f)
            self._rows = [[e, u, w], [u, r2 * d, r2 * f], [w, r2 * f, r2 * q]]
            self.pz = [f0 * f0 * self.pz[0] + qz[0]]
            if self.pb is not None:
                self.pb = [f0 * f0 * self.pb[0] + qb[0]]
            return
        (a00, a01, c0, h0), (_, a11, c1, h1), (_, _, d, f), (_, _, _, q) = rows
        p00, p01, p10, p11 = phi
        g0, g1 = g
        b00, b01 = p00 * a00 + p01 * a01, p00 * a01 + p01 * a11
        b10, b11 = p10 * a00 + p11 * a01, p10 * a01 + p11 * a11
        x0, x1 = p00 * c0 + p01 * c1, p10 * c0 + p11 * c1  # Φ c
        y0, y1 = p00 * h0 + p01 * h1, p10 * h0 + p11 * h1  # Φ h
        e00 = b00 * p00 + b01 * p01 - 2.0 * x0 * g0 + d * g0 * g0
        e01 = b00 * p10 + b01 * p11 - x0 * g1 - g0 * x1 + d * g0 * g1
        e11 = b10 * p10 + b11 * p11 - 2.0 * x1 * g1 + d * g1 * g1
        u0, u1 = ratio * (x0 - g0 * d), ratio * (x1 - g1 * d)
        w0, w1 = ratio * (y0 - g0 * f), ratio * (y1 - g1 * f)
        self._rows = [
            [e00, e01, u0, w0],
            [e01, e11, u1, w1],
            [u0, u1, r2 * d, r2 * f],
            [w0, w1, r2 * f, r2 * q],
        ]
        self.pz = _sandwich2(phi, self.pz, qz)
        if self.pb is not None:
            self.pb = _sandwich2(phi, self.pb, qb)

    def replace_measurement(self, var_new: float, corr: float) -> None:
        """The held measurement becomes a new one of variance ``var_new`` (per unit λ),
        correlated ``corr`` with the old one through their shared frame: ``ε ← a k + fresh``,
        ``k ← `` the new burst's end-frame half. The shared part carries at most the old error's
        end-frame half (``corr`` above ½ is taken as ½)."""
        n = self.n
        rows = self._rows
        d, q = rows[n][n], rows[n + 1][n + 1]
        c = min(corr, SHARED_END_SHARE)
        a = c * math.sqrt(var_new * d) / q if c > 0 and q > 0 and d > 0 else 0.0
        half = SHARED_END_SHARE * var_new
        for i in range(n):
            rows[i][n] = rows[n][i] = a * rows[i][n + 1]  # cov(e, a k)
            rows[i][n + 1] = rows[n + 1][i] = 0.0  # the new k is fresh
        rows[n][n] = var_new  # a² var k + the fresh rest
        rows[n][n + 1] = rows[n + 1][n] = half  # the new k is part of the new ε
        rows[n + 1][n + 1] = half

    def kalman_update(self, k: Sequence[float] | FloatArray) -> None:
        """``e ← (I − K C) e − K ε`` (the held measurement just replaced; ``k`` unchanged):
        ``e ← e − K ν`` with ``ν = e_z + ε``, written out (a 4×4 congruence per burst)."""
        n = self.n
        rows = self._rows
        kk = [float(x) for x in k]
        m = n + 2
        cv = [rows[0][j] + rows[n][j] for j in range(m)]  # cov(ν, ·)
        vv = cv[0] + cv[n]  # var ν
        new = [row[:] for row in rows]
        for i in range(n):
            for j in range(m):
                v = rows[i][j] - kk[i] * cv[j]
                if j < n:
                    v += -kk[j] * cv[i] + kk[i] * kk[j] * vv
                new[i][j] = v
                if j >= n:
                    new[j][i] = v
        self._rows = new
        t = [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]
        for i in range(n):
            t[i][0] -= kk[i]
        tn = t
        self.pz = _flat(_congruence(tn, _square(self.pz, n)))
        if self.pb is not None:
            self.pb = _flat(_congruence(tn, _square(self.pb, n)))

    def innovation_variance(self) -> float:
        """Variance of the innovation ``ν = y − ẑ = e_z + ε``."""
        n = self.n
        rows = self._rows
        return self.var_z + self.scale * (rows[n][n] + 2.0 * rows[0][n])

    def start(self, var_meas: float, var_second: float) -> None:
        """A filter initialised at a measurement (variance per unit λ): ``e_z = −ε`` exactly,
        half of ε in the end frame the next burst shares."""
        n = self.n
        half = SHARED_END_SHARE * float(var_meas)
        p = [[0.0] * (n + 2) for _ in range(n + 2)]
        p[0][0] = p[n][n] = float(var_meas)
        p[0][n] = p[n][0] = -float(var_meas)
        p[0][n + 1] = p[n + 1][0] = -half
        p[n][n + 1] = p[n + 1][n] = p[n + 1][n + 1] = half
        if n == 2:
            p[1][1] = float(var_second)
        self._rows = p
        self.pz = [0.0] * (n * n)
        if self.pb is not None:
            self.pb = [0.0] * (n * n)

    def copy_from(self, other: ErrorCovariance) -> None:
        """Take ``other``'s depth error and measurement blocks (a seeded filter; others zeroed)."""
        assert isinstance(other, SharedFrameCovariance)
        n, m = self.n, other.n
        idx = [0, m, m + 1] if n == 1 else [0, 1, m, m + 1]
        rows = other._rows
        self._rows = [[rows[i][j] for j in idx] for i in idx]
        self.pz = [other.pz[0]] if n == 1 else list(other.pz)
        if self.pb is not None:
            src = other.pb if other.pb is not None else [0.0] * (m * m)
            self.pb = [src[0]] if n == 1 else list(src)


def _sandwich2(phi: Mat2, p: list[float], q: Mat2) -> list[float]:
    """``Φ P Φᵀ + Q`` of row-major 2×2 floats (P symmetric)."""
    p00, p01, p10, p11 = phi
    a00, a01, _, a11 = p
    b00, b01 = p00 * a00 + p01 * a01, p00 * a01 + p01 * a11
    b10, b11 = p10 * a00 + p11 * a01, p10 * a01 + p11 * a11
    e00 = b00 * p00 + b01 * p01 + q[0]
    e01 = b00 * p10 + b01 * p11 + q[1]
    e11 = b10 * p10 + b11 * p11 + q[3]
    return [e00, e01, e01, e11]


def _congruence(t: list[list[float]], p: list[list[float]]) -> list[list[float]]:
    """``T P Tᵀ`` of small square float matrices (rows), each sum in index order (from 0.0:
    the same values, signed zeros included, as the loop below; 2×2 and 3×3 written out, the
    loop's list building and calls were ~60 µs of a burst's update)."""
    size = len(t)
    if size == 3:
        return _congruence3(t, p)
    if size == 2:
        return _congruence2(t, p)
    return _congruence_loop(t, p)


def _congruence_loop(t: list[list[float]], p: list[list[float]]) -> list[list[float]]:
    """:func:`_congruence` of any size (the reference of the written-out ones)."""
    size = len(t)
    a = [[_sum_products(t[i], [p[k][j] for k in range(size)]) for j in range(size)]
         for i in range(size)]  # fmt: skip
    return [[_sum_products(a[i], t[j]) for j in range(size)] for i in range(size)]


def _congruence2(t: list[list[float]], p: list[list[float]]) -> list[list[float]]:
    """:func:`_congruence` of 2×2 matrices written out (the same sums in the same order)."""
    t0, t1 = t
    p0, p1 = p
    t00, t01 = t0
    t10, t11 = t1
    p00, p01 = p0
    p10, p11 = p1
    a00 = 0.0 + t00 * p00 + t01 * p10
    a01 = 0.0 + t00 * p01 + t01 * p11
    a10 = 0.0 + t10 * p00 + t11 * p10
    a11 = 0.0 + t10 * p01 + t11 * p11
    return [
        [0.0 + a00 * t00 + a01 * t01, 0.0 + a00 * t10 + a01 * t11],
        [0.0 + a10 * t00 + a11 * t01, 0.0 + a10 * t10 + a11 * t11],
    ]


def _congruence3(t: list[list[float]], p: list[list[float]]) -> list[list[float]]:
    """:func:`_congruence` of 3×3 matrices written out (the same sums in the same order)."""
    t0, t1, t2 = t
    p0, p1, p2 = p
    t00, t01, t02 = t0
    t10, t11, t12 = t1
    t20, t21, t22 = t2
    p00, p01, p02 = p0
    p10, p11, p12 = p1
    p20, p21, p22 = p2
    a00 = 0.0 + t00 * p00 + t01 * p10 + t02 * p20
    a01 = 0.0 + t00 * p01 + t01 * p11 + t02 * p21
    a02 = 0.0 + t00 * p02 + t01 * p12 + t02 * p22
    a10 = 0.0 + t10 * p00 + t11 * p10 + t12 * p20
    a11 = 0.0 + t10 * p01 + t11 * p11 + t12 * p21
    a12 = 0.0 + t10 * p02 + t11 * p12 + t12 * p22
    a20 = 0.0 + t20 * p00 + t21 * p10 + t22 * p20
    a21 = 0.0 + t20 * p01 + t21 * p11 + t22 * p21
    a22 = 0.0 + t20 * p02 + t21 * p12 + t22 * p22
    return [
        [
            0.0 + a00 * t00 + a01 * t01 + a02 * t02,
            0.0 + a00 * t10 + a01 * t11 + a02 * t12,
            0.0 + a00 * t20 + a01 * t21 + a02 * t22,
        ],
        [
            0.0 + a10 * t00 + a11 * t01 + a12 * t02,
            0.0 + a10 * t10 + a11 * t11 + a12 * t12,
            0.0 + a10 * t20 + a11 * t21 + a12 * t22,
        ],
        [
            0.0 + a20 * t00 + a21 * t01 + a22 * t02,
            0.0 + a20 * t10 + a21 * t11 + a22 * t12,
            0.0 + a20 * t20 + a21 * t21 + a22 * t22,
        ],
    ]


def _sum_products(u: list[float], v: list[float]) -> float:
    """``Σ u_k v_k`` accumulated from k = 0."""
    acc = 0.0
    for a, b in zip(u, v, strict=True):
        acc += a * b
    return acc


def _square(flat: list[float], n: int) -> list[list[float]]:
    return [flat[i * n : (i + 1) * n] for i in range(n)]


def _flat(rows: list[list[float]]) -> list[float]:
    return [v for row in rows for v in row]
