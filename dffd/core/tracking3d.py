"""3D tracking of the target: position, velocity, acceleration and turn rate by multiple models.

As in the system the paper belongs to (Gaspar & Oliveira), the target's world position,
velocity, acceleration and angular speed are estimated from the single pan/tilt camera by
multiple-model adaptive estimation. Pure and deterministic: no clock, no I/O; the caller hands in
the frame time and one measurement per frame that has a contour.

**Measurement.** The target's direction (image centroid through the camera model — principal
point, pixel pitch, image distance — and the pan/tilt angles) and the fused depth ``z`` along
the optical axis, each with its σ. It is *converted* to a Cartesian world point with the
covariance propagated through the Jacobian of the conversion (:func:`cartesian_measurement`),
rather than updated by an EKF on (direction, depth). Why: the angular errors are tiny (a tenth
of a pixel is ~2·10⁻⁵ rad at f = 31 mm, p = 5 µm; the pan/tilt readback ~3.5·10⁻⁴ rad), so the
conversion's linearisation error — of order ``z σ_θ²`` — is microns, far below the depth σ; the
converted measurement is then exactly linear in the state (``H = [I 0 …]``), identical for every
model, so the models' innovation likelihoods are computed on the same quantity and IMM mixing
stays linear. The covariance is strongly elongated along the line of sight (depth σ of
centimetres, lateral σ of millimetres) and that shape is what the filters use.

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
symmetrised after every step, innovation covariances factorised by Cholesky, likelihoods in log
space. Frames are documented in ``docs/tracking3d.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from dffd.core.motion_models import (
    ACC,
    OMEGA,
    POS,
    STATE_DIM,
    VEL,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    MotionModel,
)

FloatArray = npt.NDArray[np.float64]
Vec3 = tuple[float, float, float]
TrackerKind = Literal["mmae", "imm", "cv"]
TRACKER_KINDS: tuple[TrackerKind, ...] = ("mmae", "imm", "cv")

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Pinhole back-projection: principal point (px), pixel pitch and image distance (mm)."""

    principal_point_px: tuple[float, float]
    pixel_pitch_mm: float
    image_distance_mm: float  # lens-to-sensor distance (≈ f at long range), as geometry.py uses

    @classmethod
    def centred(
        cls, image_size: tuple[int, int], pixel_pitch_mm: float, image_distance_mm: float
    ) -> CameraModel:
        """Principal point at the image centre, as :func:`dffd.core.geometry.camera_point`."""
        w, h = image_size
        return cls(((w - 1) / 2.0, (h - 1) / 2.0), pixel_pitch_mm, image_distance_mm)


@dataclass(frozen=True, slots=True)
class DirectionDepth:
    """One frame's measurement: centroid, pan/tilt and depth along the optical axis, with σ."""

    centroid_px: tuple[float, float]
    pan_deg: float
    tilt_deg: float
    z_m: float
    sigma_z_m: float
    sigma_px: float = 0.3  # centroid σ per axis
    sigma_angle_deg: float = 0.02  # pan/tilt readback σ per axis (EVI-D100: 1/14.4°/√12)


@dataclass(frozen=True, slots=True)
class Tracker3DConfig:
    """Noise densities of the bank and the combination's constants.

    Values describe the paper's setting — a small indoor robot at walking pace (≤ 1 m/s) that
    turns and stops — not a fit to any simulator run.
    """

    q_cv_m2_s3: float = 1e-4  # bank CV (quiet): velocity wanders ~1 cm/s per √s
    q_cv_single_m2_s3: float = 1e-2  # lone CV baseline, absorbs manoeuvres: ~0.1 m/s per √s
    q_ca_m2_s5: float = 2e-2  # CA white jerk: acceleration wanders ~0.14 m/s² per √s
    q_ct_m2_s3: float = 1e-4  # CT white acceleration (on top of the turn), as quiet as the CV
    q_omega_rad2_s3: float = 1e-4  # CT turn-rate random walk: ~0.01 rad/s per √s
    probability_floor: float = 1e-3  # MMAE: no model probability below this
    switch_rate_hz: float = 0.2  # IMM: rate of leaving a model (mean sojourn 5 s)
    init_sigma_v_m_s: float = 1.0  # prior on the velocity at the first measurement
    init_sigma_a_m_s2: float = 0.5
    init_sigma_omega_rad_s: float = 0.3
    max_gap_s: float = 1.0  # a longer gap between measurements restarts the track

    def bank(self) -> list[MotionModel]:
        """The multiple-model bank: CV, CA, CT."""
        return [
            ConstantVelocity(self.q_cv_m2_s3),
            ConstantAcceleration(self.q_ca_m2_s5),
            CoordinatedTurn(self.q_ct_m2_s3, self.q_omega_rad2_s3),
        ]


@dataclass(frozen=True, slots=True)
class Track3DEstimate:
    """The tracker's output at one time (world frame, SI units)."""

    t: float
    position_m: Vec3
    velocity_m_s: Vec3
    acceleration_m_s2: Vec3
    angular_speed_rad_s: float  # about the upward vertical, + = counter-clockwise from above
    position_sigma_m: Vec3  # √diag of the combined position covariance
    model_probabilities: dict[str, float] = field(default_factory=dict)


def cartesian_measurement(
    meas: DirectionDepth, camera: CameraModel
) -> tuple[FloatArray, FloatArray]:
    """World point of the measurement and its covariance (first-order propagation)."""
    k = camera.pixel_pitch_mm / camera.image_distance_mm
    du = meas.centroid_px[0] - camera.principal_point_px[0]
    dv = meas.centroid_px[1] - camera.principal_point_px[1]
    z = meas.z_m
    cam = np.array([k * du * z, k * dv * z, z])
    p, t = math.radians(meas.pan_deg), math.radians(meas.tilt_deg)
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    r_pan = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    r_tilt = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    d_pan = np.array([[-sp, 0.0, cp], [0.0, 0.0, 0.0], [-cp, 0.0, -sp]])
    d_tilt = np.array([[0.0, 0.0, 0.0], [0.0, -st, -ct], [0.0, ct, -st]])
    rot = r_pan @ r_tilt
    world = rot @ cam
    # Jacobian with respect to (u, v, z, pan, tilt).
    jac = np.empty((3, 5))
    jac[:, 0] = rot[:, 0] * (k * z)
    jac[:, 1] = rot[:, 1] * (k * z)
    jac[:, 2] = rot @ np.array([k * du, k * dv, 1.0])
    jac[:, 3] = d_pan @ r_tilt @ cam
    jac[:, 4] = r_pan @ d_tilt @ cam
    sa = math.radians(meas.sigma_angle_deg)
    var = np.array([meas.sigma_px**2, meas.sigma_px**2, meas.sigma_z_m**2, sa * sa, sa * sa])
    cov = (jac * var) @ jac.T
    return world, _sym(cov)


def mmae_probabilities(prior: FloatArray, log_likelihoods: FloatArray, floor: float) -> FloatArray:
    """Bayes' rule in log space, ``μ_j ∝ μ_j L_j``, then every μ raised to ``floor``."""
    with np.errstate(divide="ignore"):
        log_post = np.log(prior) + log_likelihoods
    log_post -= np.max(log_post)
    post = np.exp(log_post)
    post /= post.sum()
    post = np.maximum(post, floor)
    return np.asarray(post / post.sum(), dtype=np.float64)


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
        self._x = np.zeros((n, STATE_DIM))
        self._p = np.zeros((n, STATE_DIM, STATE_DIM))
        self._mu = np.full(n, 1.0 / n)
        self._t: float | None = None

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
        if self._t is None or (y_r is not None and t - self._t > self.config.max_gap_s):
            if y_r is None:
                return None
            self._start(t, y_r[0], y_r[1])
            return self.estimate()
        dt = t - self._t
        if dt > 0.0:
            self._predict(dt)
            self._t = t
        if y_r is not None:
            self._update(y_r[0], y_r[1])
        return self.estimate()

    def estimate(self) -> Track3DEstimate | None:
        """The combined estimate at the last step's time."""
        if self._t is None:
            return None
        mu = self._mu
        x = mu @ self._x
        d = self._x[:, POS] - x[POS]
        pp = np.einsum("j,jab->ab", mu, self._p[:, POS, POS]) + (d.T * mu) @ d
        omega = sum(
            float(m) * model.angular_speed(xi)
            for m, model, xi in zip(mu, self.models, self._x, strict=True)
        )
        sig = np.sqrt(np.maximum(np.diag(pp), 0.0))
        return Track3DEstimate(
            t=self._t,
            position_m=_vec3(x[POS]),
            velocity_m_s=_vec3(x[VEL]),
            acceleration_m_s2=_vec3(x[ACC]),
            angular_speed_rad_s=float(omega),
            position_sigma_m=_vec3(sig),
            model_probabilities=self.probabilities,
        )

    # -- private ----------------------------------------------------------------------------

    def _start(self, t: float, y: FloatArray, r: FloatArray) -> None:
        cfg = self.config
        x = np.zeros(STATE_DIM)
        x[POS] = y
        p = np.zeros((STATE_DIM, STATE_DIM))
        p[POS, POS] = r
        p[VEL, VEL] = np.eye(3) * cfg.init_sigma_v_m_s**2
        p[ACC, ACC] = np.eye(3) * cfg.init_sigma_a_m_s2**2
        p[OMEGA, OMEGA] = cfg.init_sigma_omega_rad_s**2
        n = len(self.models)
        self._x = np.tile(x, (n, 1))
        self._p = np.tile(p, (n, 1, 1))
        self._mu = np.full(n, 1.0 / n)
        self._t = t

    def _predict(self, dt: float) -> None:
        xs, ps = self._x, self._p
        if self.method == "imm" and len(self.models) > 1:
            pi = markov_matrix(len(self.models), self.config.switch_rate_hz, dt)
            xs, ps, self._mu = imm_mix(xs, ps, self._mu, pi)
        new_x, new_p = np.empty_like(xs), np.empty_like(ps)
        for j, model in enumerate(self.models):
            new_x[j], f, q = model.predict(xs[j], dt)
            new_p[j] = _sym(f @ ps[j] @ f.T + q)
        self._x, self._p = new_x, new_p

    def _update(self, y: FloatArray, r: FloatArray) -> None:
        loglik = np.empty(len(self.models))
        for j in range(len(self.models)):
            self._x[j], self._p[j], loglik[j] = _kf_update(self._x[j], self._p[j], y, r)
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


def _vec3(v: FloatArray) -> Vec3:
    return float(v[0]), float(v[1]), float(v[2])
