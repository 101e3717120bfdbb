"""3D tracking of the target: position, velocity, acceleration and turn rate by multiple models.

As in the system the paper belongs to (Gaspar & Oliveira), the target's world position,
velocity, acceleration and angular speed are estimated from the single pan/tilt camera by
multiple-model adaptive estimation. Pure and deterministic: no clock, no I/O; the caller hands in
the frame time and one measurement per frame that has a contour.

**Measurement** (:mod:`dffd.core.tracking3d_camera`): the target's direction and fused depth
(or apparent size), converted to a Cartesian world point with its covariance — exactly linear in
the state (``H = [I 0 …]``) and identical for every model, so the models' innovation likelihoods
are computed on the same quantity and IMM mixing stays linear. The configuration, the state
layout and the output are :mod:`dffd.core.tracking3d_types`'.

**Models** (:mod:`dffd.core.motion_models`): constant velocity, constant acceleration and a
horizontal coordinated turn with the turn rate as a state (EKF), each discretised exactly for the
frame's own ``dt``.

**Combinations.**

* MMAE — one filter per model, never interacting; model probabilities by Bayes from the
  innovation likelihoods, ``μ_j ∝ μ_j L_j`` (in log space), with a floor so no model dies
  (a model that fits again later can win again).
* IMM — the same bank with Markov mixing of the model-conditioned estimates before each
  prediction; the switching matrix is the exact discretisation over ``dt`` of a continuous-time
  chain leaving each model at rate ``switch_rate_hz``.
* CV — a single constant-velocity filter, the baseline.

The combined output is the probability-weighted mean and the spread-of-the-means covariance;
the angular speed is the probability-weighted turn rate of the models (0 for CV, the kinematic
``(v × a)·u/|v_h|²`` for CA, the state for CT). Numerics: Joseph-form updates, covariances
symmetrised after every step, the 3×3 innovation covariances inverted by cofactors, likelihoods
in log space; every model of the bank predicted, updated and combined in one compiled kernel call
each (:mod:`dffd.core.kernels_track`, with NumPy twins while numba compiles; pinned on a recorded
run: tests/test_core_tracking3d_trace.py). Frames are documented in
``docs/tracking3d.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from dffd.core import kernel_dispatch
from dffd.core.kernel_layout import (
    COMBINE_OMEGA,
    COMBINE_SIZE,
    COMBINE_SIZE_VAR,
    COMBINE_STATE,
    COMBINE_VAR,
    MODEL_CA,
    MODEL_CT,
    MODEL_CV,
    N_COMBINE,
)
from dffd.core.kernels_track_numpy import mmae_probabilities, predict_models
from dffd.core.motion_models import (
    ACC,
    OMEGA,
    POS,
    VEL,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    MotionModel,
)
from dffd.core.tracking3d_camera import CameraModel, DirectionDepth, cartesian_measurement
from dffd.core.tracking3d_types import (
    SIZE,
    TRACK_DIM,
    Track3DEstimate,
    Tracker3DConfig,
    TrackerKind,
)

FloatArray = npt.NDArray[np.float64]

_LOG_2PI = math.log(2.0 * math.pi)
_POS_IDX = np.arange(3)  # the position's indices in the state (diagonal gathers)


def markov_matrix(n: int, rate_hz: float, dt: float) -> FloatArray:
    """``exp(Λ dt)`` of a chain leaving each of ``n`` models at ``rate_hz`` for any other.

    ``Λ = λ/(n−1) (11ᵀ − n I)``: its eigenvalues are 0 (the uniform vector) and ``−nλ/(n−1)``, so
    ``exp(Λ dt) = 11ᵀ/n + (I − 11ᵀ/n) e^{−nλ dt/(n−1)}``; row i holds P(next = j | now = i).
    """
    if n == 1:
        return np.ones((1, 1))
    uniform = np.full((n, n), 1.0 / n)
    decay = math.exp(-n * rate_hz * max(dt, 0.0) / (n - 1))
    return np.asarray(uniform + (np.eye(n) - uniform) * decay, dtype=np.float64)


def imm_mix(
    states: FloatArray, covs: FloatArray, mu: FloatArray, pi: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """IMM interaction on stacked (n, 10) states and (n, 10, 10) covariances.

    Returns the mixed states and covariances (same shapes) and the predicted probabilities
    ``c_j = Σ_i π_ij μ_i``.
    """
    c = pi.T @ mu
    joint = pi * mu[:, None]  # joint[i, j] = π_ij μ_i
    safe = np.where(c > 0.0, c, 1.0)
    w = np.where(c > 0.0, joint / safe, 1.0 / len(mu))  # w[i, j] = μ_{i|j}
    mixed = w.T @ states
    d = states[:, None, :] - mixed[None, :, :]  # d[i, j] = x_i − x0_j
    spread = np.einsum("ij,ija,ijb->jab", w, d, d)
    covs_mixed = np.einsum("ij,iab->jab", w, covs) + spread
    covs_mixed = 0.5 * (covs_mixed + covs_mixed.transpose(0, 2, 1))
    return mixed, covs_mixed, np.asarray(c, dtype=np.float64)


class Tracker3D:
    """A bank of motion models combined by MMAE or IMM (or one model alone)."""

    def __init__(
        self,
        models: Sequence[MotionModel],
        method: Literal["mmae", "imm"],
        config: Tracker3DConfig | None = None,
    ) -> None:
        if not models:
            raise ValueError("a tracker needs at least one motion model")
        self.config = config or Tracker3DConfig()
        self.models = list(models)
        self.method = method
        self.names = [m.name for m in self.models]
        n = len(self.models)
        self._x = np.zeros((n, TRACK_DIM))
        self._p = np.zeros((n, TRACK_DIM, TRACK_DIM))
        self._mu = np.full(n, 1.0 / n)
        self._t: float | None = None
        self._size: tuple[float, float] | None = None  # (R̂, var) of the last size track
        self._last: Track3DEstimate | None = None  # the last step's output
        # The bank's models by kernel code (dffd.core.kernels_track), or None when a model is
        # not one of the three the kernels know (then NumPy, model by model).
        self._codes = _model_codes(self.models)
        self._q = np.array([getattr(m, "q", 0.0) for m in self.models], dtype=np.float64)
        self._q_omega = np.array(
            [getattr(m, "q_omega", 0.0) for m in self.models], dtype=np.float64
        )
        self._combined = np.empty(N_COMBINE)
        # Spare state, covariance and probability buffers a kernel writes its output into (then
        # swapped with the current ones: no allocation per step), and the log-likelihoods.
        self._spare = (np.empty((n, TRACK_DIM)), np.empty((n, TRACK_DIM, TRACK_DIM)))
        self._spare_mu = np.empty(n)
        self._loglik = np.empty(n)

    @classmethod
    def of_kind(cls, kind: TrackerKind, config: Tracker3DConfig | None = None) -> Tracker3D:
        """``mmae``/``imm`` on the config's bank, or ``cv``: its CV model alone."""
        cfg = config or Tracker3DConfig()
        if kind == "cv":
            return cls([ConstantVelocity(cfg.q_cv_single_m2_s3)], "mmae", cfg)
        return cls(cfg.bank(), kind, cfg)

    @property
    def started(self) -> bool:
        """True once a measurement has initialised the track."""
        return self._t is not None

    @property
    def probabilities(self) -> dict[str, float]:
        """Current model probabilities by model name."""
        return {name: float(mu) for name, mu in zip(self.names, self._mu, strict=True)}

    def reset(self) -> None:
        """Forget the track; the next measurement starts a new one."""
        n = len(self.models)
        self._mu = np.full(n, 1.0 / n)
        self._t = None
        self._size = None
        self._last = None

    def step(
        self, t: float, meas: DirectionDepth | None, camera: CameraModel | None = None
    ) -> Track3DEstimate | None:
        """Advance to time ``t`` and fold in the measurement (None: predict only).

        Returns None while no track exists (no measurement yet, or predict-only after a reset).
        """
        if meas is not None and camera is None:
            raise ValueError("a measurement needs the camera model to be converted")
        y_r = cartesian_measurement(meas, camera) if meas is not None and camera else None
        return self.step_cartesian(t, y_r)

    def step_cartesian(
        self, t: float, y_r: tuple[FloatArray, FloatArray] | None
    ) -> Track3DEstimate | None:
        """As :meth:`step` with an already converted measurement ``(y, R)`` (world frame)."""
        if self._restarts(t, y_r is not None):
            if y_r is None:
                return None
            self._start(t, y_r[0], y_r[1])
            return self.estimate()
        self._advance(t)
        if y_r is not None:
            self._update_models(lambda x, p: _kf_update(x, p, y_r[0], y_r[1]))
        return self.estimate()

    def step_size(
        self,
        t: float,
        unit: tuple[FloatArray, FloatArray] | None,
        size: tuple[float, float] | None = None,
    ) -> Track3DEstimate | None:
        """Advance to ``t``; fold in a size measurement and a direction-and-size measurement.

        ``unit``: the unit-size point ``m`` and its covariance (:func:`unit_size_point`): the
        position is ``p = R m`` with the size ``R`` a state (pseudo-measurement ``p − R m = 0``,
        linear in the state for the measured ``m``; noise ``R̂² Σ_m``). ``size``: ``(R, σ_R²)``,
        a measurement of the size (a burst's depth times the image size at its time). A track
        starts with both; after a gap it restarts with the size it had. Returns None while no
        track exists.
        """
        if self._restarts(t, unit is not None):
            if size is None and self._size is not None and self._t is not None:
                size = self._size
            if unit is None or size is None:
                return None
            if size[1] > (self.config.start_size_sigma_rel * size[0]) ** 2:
                return None  # too vague a size to start on (start_size_sigma_rel)
            self._start(t, size[0] * unit[0], size[0] ** 2 * unit[1])
            self._start_size(unit[0], size)
            return self.estimate()
        impl = kernel_dispatch.current()
        self._advance(t, impl)
        if size is not None:
            xs, ps = self._spare
            impl.track_size_update(self._x, self._p, size[0], size[1], xs, ps)
            self._swap()
        if unit is not None:
            xs, ps = self._spare
            mu = self._spare_mu
            m, sigma_m = np.ascontiguousarray(unit[0]), np.ascontiguousarray(unit[1])
            floor = self.config.probability_floor
            if (
                impl.track_unit_update(
                    self._x, self._p, m, sigma_m, self._mu, floor, xs, ps, self._loglik, mu
                )
                != 0
            ):
                raise np.linalg.LinAlgError(
                    f"innovation covariance is not positive definite (unit point {unit!r})"
                )
            self._swap()
            self._spare_mu, self._mu = self._mu, mu
        combined = self._combine(impl)
        if self._size is not None:
            self._size = combined[COMBINE_SIZE], combined[COMBINE_SIZE_VAR]
        return self._estimate_of(combined)

    def extrapolate(self, t: float) -> Track3DEstimate | None:
        """The last combined estimate carried to ``t`` at constant acceleration, without a
        step: a cheap output for frames that bring no measurement (the state is unchanged;
        σ is the last one). None without a track, or beyond ``max_gap_s``."""
        est = self.estimate() if self._last is None else self._last
        if est is None or not 0.0 <= t - est.t <= self.config.max_gap_s:
            return None
        dt = t - est.t
        h = 0.5 * dt * dt
        (px, py, pz), (vx, vy, vz), (ax, ay, az) = (
            est.position_m,
            est.velocity_m_s,
            est.acceleration_m_s2,
        )
        # p + (v dt + a dt²/2), v + a dt: in floats, the same operations as NumPy's.
        return Track3DEstimate(
            t,
            (px + (vx * dt + ax * h), py + (vy * dt + ay * h), pz + (vz * dt + az * h)),
            (vx + ax * dt, vy + ay * dt, vz + az * dt),
            est.acceleration_m_s2,
            est.angular_speed_rad_s,
            est.position_sigma_m,
            est.model_probabilities,
        )

    def estimate(self) -> Track3DEstimate | None:
        """The combined estimate at the last step's time."""
        if self._t is None:
            return None
        return self._estimate_of(self._combine())

    # -- private ----------------------------------------------------------------------------

    def _combine(self, impl: kernel_dispatch.KernelSet | None = None) -> list[float]:
        """The combined state, turn rate, position variances and size (kernel_layout's
        ``COMBINE_*`` slots) of the current bank (``impl``: the kernels, default current)."""
        out = self._combined
        if self._codes is not None:
            impl = kernel_dispatch.current() if impl is None else impl
            impl.track_combine(self._mu, self._x, self._p, self._codes, out)
            return out.tolist()
        mu = self._mu
        xs = self._x
        x = mu @ xs
        # Only the diagonal of the combined position covariance Σ μ_j (P_j + d_j d_jᵀ) is
        # published (σ per axis).
        d = xs[:, POS] - x[POS]
        out[COMBINE_STATE : COMBINE_STATE + 9] = x[:9]
        out[COMBINE_VAR : COMBINE_VAR + 3] = mu @ self._p[:, _POS_IDX, _POS_IDX] + mu @ (d * d)
        omega = 0.0
        for m, model, xi in zip(mu.tolist(), self.models, xs, strict=True):
            omega += m * model.angular_speed(xi)
        out[COMBINE_OMEGA] = omega
        out[COMBINE_SIZE] = float(mu @ xs[:, SIZE])
        out[COMBINE_SIZE_VAR] = float(mu @ self._p[:, SIZE, SIZE])
        return out.tolist()

    def _estimate_of(self, c: list[float]) -> Track3DEstimate:
        """The published estimate at the last step's time from :meth:`_combine`'s output."""
        assert self._t is not None
        v = COMBINE_VAR
        sig = (
            math.sqrt(max(c[v], 0.0)),
            math.sqrt(max(c[v + 1], 0.0)),
            math.sqrt(max(c[v + 2], 0.0)),
        )
        s = COMBINE_STATE
        self._last = Track3DEstimate(
            t=self._t,
            position_m=(c[s], c[s + 1], c[s + 2]),
            velocity_m_s=(c[s + 3], c[s + 4], c[s + 5]),
            acceleration_m_s2=(c[s + 6], c[s + 7], c[s + 8]),
            angular_speed_rad_s=c[COMBINE_OMEGA],
            position_sigma_m=sig,
            model_probabilities=dict(zip(self.names, self._mu.tolist(), strict=True)),
        )
        return self._last

    def _start(self, t: float, y: FloatArray, r: FloatArray) -> None:
        cfg = self.config
        x = np.zeros(TRACK_DIM)
        x[POS] = y
        p = np.zeros((TRACK_DIM, TRACK_DIM))
        p[POS, POS] = r
        p[VEL, VEL] = np.eye(3) * cfg.init_sigma_v_m_s**2
        p[ACC, ACC] = np.eye(3) * cfg.init_sigma_a_m_s2**2
        p[OMEGA, OMEGA] = cfg.init_sigma_omega_rad_s**2
        p[SIZE, SIZE] = 1.0  # unobserved by Cartesian measurements; set by _start_size
        n = len(self.models)
        self._x = np.tile(x, (n, 1))
        self._p = np.tile(p, (n, 1, 1))
        self._mu = np.full(n, 1.0 / n)
        self._t = t
        self._size = None

    def _start_size(self, m: FloatArray, size: tuple[float, float]) -> None:
        """Add the size to a track started at ``p = R m``: ``cov(p) += var m mᵀ``, ``cov(p, R)
        = var m``."""
        r_hat, var = size
        self._x[:, SIZE] = r_hat
        self._p[:, POS, POS] += var * np.outer(m, m)
        self._p[:, POS, SIZE] = var * m
        self._p[:, SIZE, POS] = var * m
        self._p[:, SIZE, SIZE] = var
        self._size = (r_hat, var)

    def _restarts(self, t: float, measured: bool) -> bool:
        """No track yet, or a measurement after a gap longer than ``max_gap_s``."""
        return self._t is None or (measured and t - self._t > self.config.max_gap_s)

    def _advance(self, t: float, impl: kernel_dispatch.KernelSet | None = None) -> None:
        assert self._t is not None
        dt = t - self._t
        if dt > 0.0:
            self._predict(dt, impl)
            self._t = t

    def _predict(self, dt: float, impl: kernel_dispatch.KernelSet | None = None) -> None:
        xs, ps = self._x, self._p
        if self.method == "imm" and len(self.models) > 1:
            pi = markov_matrix(len(self.models), self.config.switch_rate_hz, dt)
            xs, ps, self._mu = imm_mix(xs, ps, self._mu, pi)
        # F = diag(F_model, 1) and Q = diag(Q_model, q_size dt): the size is carried by every
        # model; every model in one kernel call (or one stacked NumPy product).
        new_x, new_p = self._spare
        q_size = self.config.q_size_m2_s
        if self._codes is None:
            predict_models(self.models, xs, ps, dt, q_size, new_x, new_p)
        else:
            impl = kernel_dispatch.current() if impl is None else impl
            impl.track_predict(
                xs, ps, self._codes, self._q, self._q_omega, dt, q_size, new_x, new_p
            )
        self._swap()

    def _swap(self) -> None:
        """The spare buffers (just written) become the state; the old state the spare."""
        (new_x, new_p), self._spare = self._spare, (self._x, self._p)
        self._x, self._p = new_x, new_p

    def _update_models(
        self, update: Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray, float]]
    ) -> None:
        """Update every model with ``update(x, P) -> (x⁺, P⁺, log L)``; then the probabilities."""
        loglik = np.empty(len(self.models))
        for j in range(len(self.models)):
            self._x[j], self._p[j], loglik[j] = update(self._x[j], self._p[j])
        self._update_probabilities(loglik)

    def _update_probabilities(self, loglik: FloatArray) -> None:
        if len(self.models) > 1:
            floor = self.config.probability_floor
            self._mu = mmae_probabilities(self._mu, loglik, floor)


class Tracker3DBank:
    """Trackers of several kinds fed the same measurements (the first kind is the published one).

    The service runs ``("mmae",)``; the bench adds ``"imm"`` and ``"cv"`` to compare them on the
    same frames.
    """

    def __init__(
        self, kinds: Sequence[TrackerKind] = ("mmae",), config: Tracker3DConfig | None = None
    ) -> None:
        if not kinds:
            raise ValueError("a tracker bank needs at least one tracker kind")
        self.kinds = tuple(kinds)
        self.trackers = {kind: Tracker3D.of_kind(kind, config) for kind in self.kinds}

    def step(
        self, t: float, y_r: tuple[FloatArray, FloatArray] | None
    ) -> dict[str, Track3DEstimate]:
        """Step every tracker (see :meth:`Tracker3D.step_cartesian`); those with a track."""
        out: dict[str, Track3DEstimate] = {}
        for kind, tracker in self.trackers.items():
            est = tracker.step_cartesian(t, y_r)
            if est is not None:
                out[kind] = est
        return out

    def step_size(
        self,
        t: float,
        unit: tuple[FloatArray, FloatArray] | None,
        size: tuple[float, float] | None = None,
    ) -> dict[str, Track3DEstimate]:
        """Step every tracker (see :meth:`Tracker3D.step_size`); those with a track."""
        out: dict[str, Track3DEstimate] = {}
        for kind, tracker in self.trackers.items():
            est = tracker.step_size(t, unit, size)
            if est is not None:
                out[kind] = est
        return out

    def extrapolate(self, t: float) -> dict[str, Track3DEstimate]:
        """Every tracker's :meth:`Tracker3D.extrapolate` to ``t``; those with a track."""
        out: dict[str, Track3DEstimate] = {}
        for kind, tracker in self.trackers.items():
            est = tracker.extrapolate(t)
            if est is not None:
                out[kind] = est
        return out

    def reset(self) -> None:
        """Forget every track."""
        for tracker in self.trackers.values():
            tracker.reset()


def _kf_update(
    x: FloatArray, p: FloatArray, y: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Joseph-form update with ``H = [I₃ 0]``; returns (x⁺, P⁺, log-likelihood of y)."""
    nu = y - x[POS]
    s_inv, logdet = _inv3_logdet(p[POS, POS] + r)
    maha = float(nu @ s_inv @ nu)
    loglik = -0.5 * (maha + logdet + 3.0 * _LOG_2PI)
    gain = p[:, POS] @ s_inv  # P Hᵀ S⁻¹
    x_new = x + gain @ nu
    # Joseph form (I − KH) P (I − KH)ᵀ + K R Kᵀ, with A = (I − KH) P = P − K (H P):
    # (I − KH) P (I − KH)ᵀ = A − (A Hᵀ) Kᵀ — exact for any K, and only 10×3 products.
    a = p - gain @ p[POS, :]
    p_new = a - a[:, POS] @ gain.T + gain @ r @ gain.T
    return x_new, _sym(p_new), loglik


def _unit_update(
    x: FloatArray, p: FloatArray, m: FloatArray, sigma_m: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Joseph-form update on the pseudo-measurement ``0 = p − R m`` (``H = [I₃ 0 … −m]``).

    Its noise is ``R̂² Σ_m``; returns (x⁺, P⁺, log-likelihood).
    """
    size = float(x[SIZE])
    nu = size * m - x[POS]
    pht = p[:, POS] - np.outer(p[:, SIZE], m)  # P Hᵀ
    rn = (size * size) * sigma_m
    s_inv, logdet = _inv3_logdet(pht[POS, :] - np.outer(m, pht[SIZE, :]) + rn)
    maha = float(nu @ s_inv @ nu)
    loglik = -0.5 * (maha + logdet + 3.0 * _LOG_2PI)
    gain = pht @ s_inv
    x_new = x + gain @ nu
    a = p - gain @ pht.T  # (I − KH) P
    aht = a[:, POS] - np.outer(a[:, SIZE], m)  # A Hᵀ
    p_new = a - aht @ gain.T + gain @ rn @ gain.T
    return x_new, _sym(p_new), loglik


def _inv3_logdet(s: FloatArray) -> tuple[FloatArray, float]:
    """Inverse and log-determinant of a symmetric positive-definite 3×3, by cofactors."""
    (a, b, c), (_, d, e), (_, _, f) = s.tolist()
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * c00 + b * c01 + c * c02
    if not det > 0.0:
        raise np.linalg.LinAlgError(f"innovation covariance is not positive definite: {s!r}")
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    inv = np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]]) / det
    return inv, math.log(det)


def _sym(m: FloatArray) -> FloatArray:
    return np.asarray(0.5 * (m + m.T), dtype=np.float64)


def _model_codes(models: Sequence[MotionModel]) -> npt.NDArray[np.int64] | None:
    """The kernel code of every model, or None when one is not a model the kernels know."""
    known = {ConstantVelocity: MODEL_CV, ConstantAcceleration: MODEL_CA, CoordinatedTurn: MODEL_CT}
    codes = [known.get(type(m)) for m in models]
    if any(c is None for c in codes):
        return None
    return np.array(codes, dtype=np.int64)
