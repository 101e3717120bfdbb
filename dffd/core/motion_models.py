"""Motion models of the 3D tracker, each discretised exactly for any sampling interval ``dt``.

Every model works on the same 10-element state so that the multiple-model combinations (MMAE,
IMM) can mix and average states directly::

    x = [px, py, pz, vx, vy, vz, ax, ay, az, ω]     (world frame, m, m/s, m/s², rad/s)

World frame (as :mod:`dffd.core.geometry`): the camera frame at pan = tilt = 0, x right, y down,
z forward; the vertical is ``y`` (pointing down), the horizontal plane is x–z. ``ω`` is the
signed angular speed of the velocity about the *upward* vertical ``u = −y``: positive turns
x (right) towards z (forward), i.e. counter-clockwise seen from above.

* :class:`ConstantVelocity` — white acceleration noise of spectral density ``q`` on each axis;
  ``a`` is identically zero, ``ω`` is carried unchanged (it is not part of the model).
* :class:`ConstantAcceleration` — white jerk noise (Wiener-process acceleration).
* :class:`CoordinatedTurn` — the horizontal velocity rotates at the rate ``ω``, which is a state
  (random walk of density ``q_omega``): ``v̇_h = ω J v_h`` with ``J = [[0, −1], [1, 0]]`` in
  (x, z); the vertical axis is constant velocity; the acceleration is the deterministic output
  ``a_h = ω J v_h`` (``a_y = 0``). Nonlinear in ``ω``: :meth:`CoordinatedTurn.predict` returns
  the exact transition of the mean and its Jacobian (EKF).

``predict(x, dt) -> (x⁻, F, Q)``: the propagated state, the transition matrix (the Jacobian for
the turn model) and the process-noise covariance, all in closed form — ``F = exp(A dt)`` and
``Q = ∫₀^dt exp(Aτ) G Qc Gᵀ exp(Aτ)ᵀ dτ`` for the continuous model — checked against the
matrix exponential (Van Loan) in the tests. For the turn model ``Q`` is exact at the current
``ω``; the coupling of ω's own noise into position and velocity (second order in ``dt``) is
neglected, as in every EKF of this model.
"""

from __future__ import annotations

import functools
import math
from typing import Protocol

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

STATE_DIM = 10
POS = slice(0, 3)
VEL = slice(3, 6)
ACC = slice(6, 9)
OMEGA = 9
# Horizontal axes (x, z) and the vertical (y, pointing down) inside each 3-vector.
HORIZONTAL = (0, 2)
VERTICAL = 1
_PX, _PY, _PZ, _VX, _VY, _VZ, _AX, _AY, _AZ = range(9)

# Below this |ω dt| the turn model's trigonometric ratios switch to their Taylor series (the
# closed forms cancel catastrophically as θ → 0; the series' first omitted terms are ~θ⁶).
_SMALL_TURN = 1e-2
# Memoised CV/CA matrices: frames come at a few distinct intervals (the frame period, a dropped
# frame's double), and MMAE, IMM and the CV baseline step with the same dt each frame.
_DT_CACHE = 16
# Horizontal speed (m/s) below which the turn rate computed from v and a is not trusted: its
# error is the lateral acceleration error over the speed, and the CA model's acceleration is
# uncertain to ~0.05 m/s² — at 0.2 m/s that is already 0.25 rad/s. Regularised by max(|v_h|, this).
MIN_TURN_SPEED_M_S = 0.2
# kron(block, I₃) as a scatter: block[i, j] lands at (3i + k, 3j + k) for k = 0, 1, 2.
_KRON_ROWS = np.array([3 * i + k for i in range(3) for j in range(3) for k in range(3)])
_KRON_COLS = np.array([3 * j + k for i in range(3) for j in range(3) for k in range(3)])


class MotionModel(Protocol):
    """One model of the bank."""

    name: str

    def predict(self, x: FloatArray, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(state propagated over ``dt``, transition matrix or Jacobian, process noise)."""
        ...

    def angular_speed(self, x: FloatArray) -> float:
        """The turn rate (rad/s, about the upward vertical) this model attributes to ``x``."""
        ...


class ConstantVelocity:
    """Nearly constant velocity: white acceleration of density ``q`` (m²/s³) on every axis."""

    def __init__(self, q: float, name: str = "cv") -> None:
        if q < 0.0:
            raise ValueError(f"CV process noise density must be ≥ 0 (got {q})")
        self.name = name
        self.q = q

    def predict(self, x: FloatArray, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Exact discretisation; the acceleration state is reset to zero."""
        f, q = _cv_matrices(self.q, dt)
        return f @ x, f, q

    def angular_speed(self, x: FloatArray) -> float:
        """A straight line: no turn."""
        return 0.0


class ConstantAcceleration:
    """Nearly constant acceleration: white jerk of density ``q`` (m²/s⁵) on every axis."""

    def __init__(self, q: float, name: str = "ca") -> None:
        if q < 0.0:
            raise ValueError(f"CA process noise density must be ≥ 0 (got {q})")
        self.name = name
        self.q = q

    def predict(self, x: FloatArray, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Exact discretisation of the triple integrator."""
        f, q = _ca_matrices(self.q, dt)
        return f @ x, f, q

    def angular_speed(self, x: FloatArray) -> float:
        """Turn rate of the velocity under the estimated acceleration."""
        return kinematic_turn_rate(x[VEL], x[ACC])


class CoordinatedTurn:
    """Horizontal coordinated turn with the turn rate as a state (EKF).

    ``q`` (m²/s³): white acceleration density on each axis (isotropic in the horizontal plane,
    so the rotation leaves it unchanged); ``q_omega`` (rad²/s³): random-walk density of ω.
    """

    def __init__(self, q: float, q_omega: float, name: str = "ct") -> None:
        if q < 0.0 or q_omega < 0.0:
            raise ValueError(f"CT process noise densities must be ≥ 0 (got {q}, {q_omega})")
        self.name = name
        self.q = q
        self.q_omega = q_omega

    def predict(self, x: FloatArray, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Exact mean transition, its Jacobian, and the exact noise at the current ω."""
        omega = float(x[OMEGA])
        theta = omega * dt
        c, s = math.cos(theta), math.sin(theta)
        f1, f2, d1, d2 = _turn_ratios(theta)
        # Rotations of the horizontal plane as complex numbers on (x, z): R(θ) = c + i s, and
        # ∫₀^dt R(ωτ) dτ = dt (f1 + i f2), whose ω-derivative is dt² (d1 + i d2).
        m_re, m_im = dt * f1, dt * f2
        dm_re, dm_im = dt * dt * d1, dt * dt * d2
        xl = x.tolist()  # plain floats: ~100 scalar writes cost less on a list than an array
        vx, vz = xl[_VX], xl[_VZ]
        nvx, nvz = c * vx - s * vz, s * vx + c * vz  # R v_h
        jvx, jvz = -nvz, nvx  # J R v_h

        out = list(xl)
        out[_PX] = xl[_PX] + m_re * vx - m_im * vz
        out[_PZ] = xl[_PZ] + m_im * vx + m_re * vz
        out[_VX], out[_VZ] = nvx, nvz
        out[_AX], out[_AZ] = omega * jvx, omega * jvz
        out[_PY] = xl[_PY] + dt * xl[_VY]
        out[_AY] = 0.0

        f = [0.0] * (STATE_DIM * STATE_DIM)  # row-major STATE_DIM × STATE_DIM
        for i in (_PX, _PZ, _PY, _VY, OMEGA):
            f[i * STATE_DIM + i] = 1.0
        f[_PY * STATE_DIM + _VY] = dt
        _set_complex(f, _PX, _PZ, _VX, _VZ, m_re, m_im)
        _set_complex(f, _VX, _VZ, _VX, _VZ, c, s)
        _set_complex(f, _AX, _AZ, _VX, _VZ, -omega * s, omega * c)  # ω J R = ω i (c + i s)
        f[_PX * STATE_DIM + OMEGA] = dm_re * vx - dm_im * vz
        f[_PZ * STATE_DIM + OMEGA] = dm_im * vx + dm_re * vz
        # dR/dω = dt J R
        f[_VX * STATE_DIM + OMEGA], f[_VZ * STATE_DIM + OMEGA] = dt * jvx, dt * jvz
        # d(ω J R v)/dω = J R v + ω J (dt J R v) = J R v − ω dt R v   (J² = −I)
        f[_AX * STATE_DIM + OMEGA] = jvx - omega * dt * nvx
        f[_AZ * STATE_DIM + OMEGA] = jvz - omega * dt * nvz

        qpp, qpv_re, qpv_im = _turn_noise(theta, dt)
        qd = self.q
        q = [0.0] * (STATE_DIM * STATE_DIM)
        # cov(p_h, v_h) = q (qpv_re + i qpv_im); cov(v_h, v_h) = q dt; the acceleration
        # a_h = ω J v_h carries the velocity noise mapped by ω J (= ω i).
        _set_complex(q, _PX, _PZ, _PX, _PZ, qd * qpp, 0.0)
        _set_complex(q, _PX, _PZ, _VX, _VZ, qd * qpv_re, qd * qpv_im)
        _set_complex(q, _VX, _VZ, _VX, _VZ, qd * dt, 0.0)
        # cov(p, a) = cov(p, v) (ωJ)ᵀ = q (re + i im)(−iω) = q ω (im − i re)
        _set_complex(q, _PX, _PZ, _AX, _AZ, qd * omega * qpv_im, -qd * omega * qpv_re)
        # cov(v, a) = q dt (ωJ)ᵀ = −i q dt ω; cov(a, a) = q dt ω²
        _set_complex(q, _VX, _VZ, _AX, _AZ, 0.0, -qd * dt * omega)
        _set_complex(q, _AX, _AZ, _AX, _AZ, qd * dt * omega * omega, 0.0)
        _mirror_upper(q, (_PX, _PZ, _VX, _VZ, _AX, _AZ))
        q[_PY * STATE_DIM + _PY] = qd * dt**3 / 3.0
        q[_PY * STATE_DIM + _VY] = q[_VY * STATE_DIM + _PY] = qd * dt**2 / 2.0
        q[_VY * STATE_DIM + _VY] = qd * dt
        q[OMEGA * STATE_DIM + OMEGA] = self.q_omega * dt
        shape = (STATE_DIM, STATE_DIM)
        return np.array(out), np.array(f).reshape(shape), np.array(q).reshape(shape)

    def angular_speed(self, x: FloatArray) -> float:
        """The turn-rate state."""
        return float(x[OMEGA])


def kinematic_turn_rate(v: FloatArray, a: FloatArray) -> float:
    """``((v × a) · u) / |v_h|²`` about the upward vertical ``u = −y`` (regularised at rest)."""
    vx, vz, ax, az = float(v[0]), float(v[2]), float(a[0]), float(a[2])
    speed2 = max(vx * vx + vz * vz, MIN_TURN_SPEED_M_S**2)
    return (vx * az - vz * ax) / speed2


# -- private helpers ------------------------------------------------------------------------


@functools.lru_cache(maxsize=_DT_CACHE)
def _cv_matrices(q: float, dt: float) -> tuple[FloatArray, FloatArray]:
    block_f = np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    block_q = q * np.array(
        [[dt**3 / 3.0, dt**2 / 2.0, 0.0], [dt**2 / 2.0, dt, 0.0], [0.0, 0.0, 0.0]]
    )
    return _per_axis(block_f, block_q)


@functools.lru_cache(maxsize=_DT_CACHE)
def _ca_matrices(q: float, dt: float) -> tuple[FloatArray, FloatArray]:
    block_f = np.array([[1.0, dt, dt * dt / 2.0], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    block_q = q * np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )
    return _per_axis(block_f, block_q)


def _per_axis(block_f: FloatArray, block_q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lift a 3×3 (p, v, a) block to the 10-state, same on every axis; ω carried, noiseless."""
    f = np.zeros((STATE_DIM, STATE_DIM))
    q = np.zeros((STATE_DIM, STATE_DIM))
    # kron(block, I₃) written in place: element (3i + k, 3j + k) = block[i, j].
    f[_KRON_ROWS, _KRON_COLS] = np.repeat(block_f, 3, axis=1).ravel()
    q[_KRON_ROWS, _KRON_COLS] = np.repeat(block_q, 3, axis=1).ravel()
    f[OMEGA, OMEGA] = 1.0
    f.flags.writeable = False  # shared through the cache
    q.flags.writeable = False
    return f, q


def _turn_ratios(theta: float) -> tuple[float, float, float, float]:
    """sin θ/θ, (1 − cos θ)/θ and their θ-derivatives."""
    if abs(theta) < _SMALL_TURN:
        t2 = theta * theta
        f1 = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        f2 = theta * (0.5 - t2 / 24.0 + t2 * t2 / 720.0)
        d1 = theta * (-1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0)
        d2 = 0.5 - t2 / 8.0 + t2 * t2 / 144.0
        return f1, f2, d1, d2
    c, s = math.cos(theta), math.sin(theta)
    f1 = s / theta
    f2 = (1.0 - c) / theta
    d1 = (theta * c - s) / (theta * theta)
    d2 = (theta * s - (1.0 - c)) / (theta * theta)
    return f1, f2, d1, d2


def _turn_noise(theta: float, dt: float) -> tuple[float, float, float]:
    """Per unit density: Q_pp = a I, Q_pv = b I + c J for the horizontal turn (see tests).

    With rotations as complex numbers, ``M(τ) = (e^{iωτ} − 1)/(iω)``,
    ``Q_pp = ∫|M|² = 2(dt − sin θ/ω)/ω²`` and
    ``Q_pv = ∫ M e^{−iωτ} = (1 − cos θ)/ω² − i(dt − sin θ/ω)/ω``.
    """
    if abs(theta) < _SMALL_TURN:
        t2 = theta * theta
        a = dt**3 * (1.0 / 3.0 - t2 / 60.0 + t2 * t2 / 2520.0)  # 2(θ − sin θ)/θ³
        b = dt**2 * (0.5 - t2 / 24.0 + t2 * t2 / 720.0)  # (1 − cos θ)/θ²
        c = -(dt**2) * theta * (1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)  # −(θ − sin θ)/θ²
        return a, b, c
    s, co = math.sin(theta), math.cos(theta)
    a = dt**3 * 2.0 * (theta - s) / theta**3
    b = dt**2 * (1.0 - co) / theta**2
    c = -(dt**2) * (theta - s) / theta**2
    return a, b, c


def _set_complex(  # noqa: PLR0917 - a block address and a complex value
    m: list[float], r0: int, r1: int, c0: int, c1: int, re: float, im: float
) -> None:
    """Write the 2×2 block of the complex number re + i·im (= re I + im J) at rows/columns of
    the row-major STATE_DIM × STATE_DIM matrix ``m``."""
    m[r0 * STATE_DIM + c0] = re
    m[r0 * STATE_DIM + c1] = -im
    m[r1 * STATE_DIM + c0] = im
    m[r1 * STATE_DIM + c1] = re


def _mirror_upper(m: list[float], order: tuple[int, ...]) -> None:
    """Fill the blocks below the diagonal (in ``order``) from those above: ``m = mᵀ`` there
    (row-major STATE_DIM × STATE_DIM ``m``)."""
    for i, a in enumerate(order):
        for b in order[i + 1 :]:
            m[b * STATE_DIM + a] = m[a * STATE_DIM + b]
