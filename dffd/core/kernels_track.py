"""Compiled kernels of the 3D tracker (numba, ``nogil``): its bank's predict, update, combine.

The multiple-model bank (:mod:`dffd.core.tracking3d`) works on three 11-element states and
11×11 covariances, where NumPy's per-call overhead (~1-5 µs a call, ~60 calls a tracking frame)
was the whole cost (~0.2 ms a frame). These kernels do the same arithmetic in one call each,
written out as loops: the sums run in another order than NumPy's BLAS products, so results
agree with the NumPy twins (:mod:`dffd.core.kernels_track_numpy`, dispatched through
:mod:`dffd.core.kernels_numpy`) to rounding (the tests assert 1e-9, as the recorded run of
tests/test_core_tracking3d_trace.py does).

The models are the bank's own (:mod:`dffd.core.motion_models`), by code
(:data:`dffd.core.kernel_layout.MODEL_CV` …): constant velocity and acceleration (the transition
``kron(block, I₃)`` with ω carried) and the coordinated turn (exact mean, Jacobian, noise at the
current ω), each with the size state ``R`` carried (``Q_RR = q_size dt``). The measurement the
bank takes, a direction and depth as a world point with its covariance, is :func:`cartesian_point`.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core import motion_models as _models
from dffd.core.kernel_jit import jit as _jit
from dffd.core.kernel_layout import (
    COMBINE_OMEGA,
    COMBINE_SIZE,
    COMBINE_SIZE_VAR,
    COMBINE_STATE,
    COMBINE_VAR,
    MODEL_CA,
    MODEL_CT,
)

__all__ = [
    "cartesian_point",
    "track_combine",
    "track_predict",
    "track_size_update",
    "track_unit_update",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_D = 11  # the tracker's state: the models' 10 elements and the size R
_SIZE = 10
_OMEGA = 9
_PX, _PY, _PZ, _VX, _VY, _VZ, _AX, _AY, _AZ = range(9)
_SMALL_TURN = _models._SMALL_TURN  # the model's own series switch
_MIN_TURN_SPEED2 = _models.MIN_TURN_SPEED_M_S**2
_LOG_2PI = math.log(2.0 * math.pi)

_M, _V = "float64[:, ::1]", "float64[::1]"
_T = "float64[:, :, ::1]"


# -- helpers (compiled first: a kernel is compiled where it is defined) -------------------------
@_jit(f"void({_M})")
def _symmetrise(m: FloatArray) -> None:
    """``m ← (m + mᵀ)/2`` in place (the diagonal is unchanged)."""
    n = m.shape[0]
    for i in range(n):
        for k in range(i + 1, n):
            v = (m[i, k] + m[k, i]) * 0.5
            m[i, k] = v
            m[k, i] = v


@_jit(f"void(boolean, float64, float64, {_M}, {_M})")
def _kinematic(ca: bool, dt: float, qd: float, f: FloatArray, qm: FloatArray) -> None:
    """CV (``ca`` False) or CA transition and noise, ``kron(block, I₃)`` and ω carried."""
    dt2 = dt * dt
    dt3 = dt2 * dt
    if ca:
        bf = ((1.0, dt, dt2 / 2.0), (0.0, 1.0, dt), (0.0, 0.0, 1.0))
        dt4 = dt3 * dt
        bq = (
            (qd * (dt4 * dt / 20.0), qd * (dt4 / 8.0), qd * (dt3 / 6.0)),
            (qd * (dt4 / 8.0), qd * (dt3 / 3.0), qd * (dt2 / 2.0)),
            (qd * (dt3 / 6.0), qd * (dt2 / 2.0), qd * dt),
        )
    else:
        bf = ((1.0, dt, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 0.0))
        bq = (
            (qd * (dt3 / 3.0), qd * (dt2 / 2.0), 0.0),
            (qd * (dt2 / 2.0), qd * dt, 0.0),
            (0.0, 0.0, 0.0),
        )
    for i in range(3):
        for j in range(3):
            for k in range(3):
                f[3 * i + k, 3 * j + k] = bf[i][j]
                qm[3 * i + k, 3 * j + k] = bq[i][j]
    f[_OMEGA, _OMEGA] = 1.0


@_jit(f"void({_M}, int64, int64, int64, int64, float64, float64)")
def _complex(  # noqa: PLR0917 - a block address and a complex value
    m: FloatArray, r0: int, r1: int, c0: int, c1: int, re: float, im: float
) -> None:
    """The 2×2 block of re + i·im (= re I + im J) at rows r0, r1 and columns c0, c1."""
    m[r0, c0] = re
    m[r0, c1] = -im
    m[r1, c0] = im
    m[r1, c1] = re


@_jit(f"void({_V}, float64, float64, float64, {_M}, {_M}, {_V})")
def _turn(  # noqa: PLR0917 - numba kernels take positional arguments
    x: FloatArray,
    dt: float,
    qd: float,
    q_omega: float,
    f: FloatArray,
    qm: FloatArray,
    xo: FloatArray,
) -> None:
    """The coordinated turn (motion_models.CoordinatedTurn.predict): mean, Jacobian, noise."""
    omega = x[_OMEGA]
    theta = omega * dt
    c, s = math.cos(theta), math.sin(theta)
    t2 = theta * theta
    if abs(theta) < _SMALL_TURN:
        f1 = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        f2 = theta * (0.5 - t2 / 24.0 + t2 * t2 / 720.0)
        d1 = theta * (-1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0)
        d2 = 0.5 - t2 / 8.0 + t2 * t2 / 144.0
        qpp = dt * dt * dt * (1.0 / 3.0 - t2 / 60.0 + t2 * t2 / 2520.0)
        qpv_re = dt * dt * (0.5 - t2 / 24.0 + t2 * t2 / 720.0)
        qpv_im = -(dt * dt) * theta * (1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)
    else:
        f1 = s / theta
        f2 = (1.0 - c) / theta
        d1 = (theta * c - s) / t2
        d2 = (theta * s - (1.0 - c)) / t2
        qpp = dt * dt * dt * 2.0 * (theta - s) / (t2 * theta)
        qpv_re = dt * dt * (1.0 - c) / t2
        qpv_im = -(dt * dt) * (theta - s) / t2
    m_re, m_im = dt * f1, dt * f2
    dm_re, dm_im = dt * dt * d1, dt * dt * d2
    vx, vz = x[_VX], x[_VZ]
    nvx, nvz = c * vx - s * vz, s * vx + c * vz  # R v_h
    jvx, jvz = -nvz, nvx  # J R v_h
    for i in range(10):
        xo[i] = x[i]
    xo[_PX] = x[_PX] + m_re * vx - m_im * vz
    xo[_PZ] = x[_PZ] + m_im * vx + m_re * vz
    xo[_VX], xo[_VZ] = nvx, nvz
    xo[_AX], xo[_AZ] = omega * jvx, omega * jvz
    xo[_PY] = x[_PY] + dt * x[_VY]
    xo[_AY] = 0.0
    for i in (_PX, _PZ, _PY, _VY, _OMEGA):
        f[i, i] = 1.0
    f[_PY, _VY] = dt
    _complex(f, _PX, _PZ, _VX, _VZ, m_re, m_im)
    _complex(f, _VX, _VZ, _VX, _VZ, c, s)
    _complex(f, _AX, _AZ, _VX, _VZ, -omega * s, omega * c)
    f[_PX, _OMEGA] = dm_re * vx - dm_im * vz
    f[_PZ, _OMEGA] = dm_im * vx + dm_re * vz
    f[_VX, _OMEGA], f[_VZ, _OMEGA] = dt * jvx, dt * jvz
    f[_AX, _OMEGA] = jvx - omega * dt * nvx
    f[_AZ, _OMEGA] = jvz - omega * dt * nvz
    _complex(qm, _PX, _PZ, _PX, _PZ, qd * qpp, 0.0)
    _complex(qm, _PX, _PZ, _VX, _VZ, qd * qpv_re, qd * qpv_im)
    _complex(qm, _VX, _VZ, _VX, _VZ, qd * dt, 0.0)
    _complex(qm, _PX, _PZ, _AX, _AZ, qd * omega * qpv_im, -qd * omega * qpv_re)
    _complex(qm, _VX, _VZ, _AX, _AZ, 0.0, -qd * dt * omega)
    _complex(qm, _AX, _AZ, _AX, _AZ, qd * dt * omega * omega, 0.0)
    order = (_PX, _PZ, _VX, _VZ, _AX, _AZ)
    for i in range(6):
        for k in range(i + 1, 6):
            qm[order[k], order[i]] = qm[order[i], order[k]]
    qm[_PY, _PY] = qd * (dt * dt * dt) / 3.0
    qm[_PY, _VY] = qd * (dt * dt) / 2.0
    qm[_VY, _PY] = qm[_PY, _VY]
    qm[_VY, _VY] = qd * dt
    qm[_OMEGA, _OMEGA] = q_omega * dt


# -- the kernels ------------------------------------------------------------------------------
@_jit(f"void({_M}, {_T}, int64[::1], {_V}, {_V}, float64, float64, {_M}, {_T})")
def track_predict(  # noqa: PLR0917 - numba kernels take positional arguments
    xs: FloatArray,
    ps: FloatArray,
    codes: IntArray,
    q: FloatArray,
    q_omega: FloatArray,
    dt: float,
    q_size: float,
    xs_out: FloatArray,
    ps_out: FloatArray,
) -> None:
    """Every model's prediction over ``dt``: ``x⁻ = f(x)``, ``P⁻ = sym(F P Fᵀ + Q)``.

    ``codes[j]``: model j's kind; ``q[j]`` its noise density, ``q_omega[j]`` the turn model's ω
    density. The size is carried with the random-walk density ``q_size``.
    """
    f = np.zeros((_D, _D))
    qm = np.zeros((_D, _D))
    tmp = np.empty((_D, _D))
    nz = np.empty((_D, _D), dtype=np.int64)  # row i's non-zero columns of F, in order
    nnz = np.empty(_D, dtype=np.int64)
    for j in range(xs.shape[0]):
        f[:, :] = 0.0
        qm[:, :] = 0.0
        x = xs[j]
        xo = xs_out[j]
        code = codes[j]
        qd = q[j]
        if code == MODEL_CT:
            _turn(x, dt, qd, q_omega[j], f, qm, xo)
        else:
            _kinematic(code == MODEL_CA, dt, qd, f, qm)
            for i in range(10):
                acc = 0.0
                for k in range(10):
                    acc += f[i, k] * x[k]
                xo[i] = acc
        f[_SIZE, _SIZE] = 1.0
        qm[_SIZE, _SIZE] = q_size * dt
        xo[_SIZE] = x[_SIZE]
        # F is sparse (at most 4 non-zeros a row of 11): the products skip its zeros. A skipped
        # term is an exact ±0 in the dense sum, so every entry is the same value as F P Fᵀ
        # summed densely in index order.
        for i in range(_D):
            cnt = 0
            for k in range(_D):
                if f[i, k] != 0.0:
                    nz[i, cnt] = k
                    cnt += 1
            nnz[i] = cnt
        p = ps[j]
        for i in range(_D):
            for k in range(_D):
                acc = 0.0
                for e in range(nnz[i]):
                    m = nz[i, e]
                    acc += f[i, m] * p[m, k]
                tmp[i, k] = acc
        po = ps_out[j]
        for i in range(_D):
            for k in range(_D):
                acc = 0.0
                for e in range(nnz[k]):
                    m = nz[k, e]
                    acc += tmp[i, m] * f[k, m]
                po[i, k] = acc + qm[i, k]
        _symmetrise(po)


@_jit(f"int64({_M}, {_T}, {_V}, {_M}, {_V}, float64, {_M}, {_T}, {_V}, {_V})")
def track_unit_update(  # noqa: PLR0917 - numba kernels take positional arguments
    xs: FloatArray,
    ps: FloatArray,
    m: FloatArray,
    sigma_m: FloatArray,
    mu: FloatArray,
    floor: float,
    xs_out: FloatArray,
    ps_out: FloatArray,
    loglik: FloatArray,
    mu_out: FloatArray,
) -> int:
    """Joseph-form update of every model on the pseudo-measurement ``0 = p − R m``.

    ``H = [I₃ 0 … −m]``, noise ``R̂² Σ_m``; the innovation covariance symmetrised and inverted by
    cofactors; ``loglik[j]`` the Gaussian log-likelihood of model j's innovation; ``mu_out``
    the models' probabilities after it (``kernels_track_numpy.mmae_probabilities`` of ``mu``
    with ``floor``; ``mu`` itself for a bank of one). Returns 0, or 1 when an innovation
    covariance is not positive definite (the outputs are then undefined).
    """
    pht = np.empty((_D, 3))
    gain = np.empty((_D, 3))
    a = np.empty((_D, _D))
    w = np.empty((_D, 3))
    rn = np.empty((3, 3))
    s = np.empty((3, 3))
    nu = np.empty(3)
    for j in range(xs.shape[0]):
        x = xs[j]
        p = ps[j]
        size = x[_SIZE]
        for c in range(3):
            nu[c] = size * m[c] - x[c]
        for i in range(_D):
            for c in range(3):
                pht[i, c] = p[i, c] - p[i, _SIZE] * m[c]
        size2 = size * size
        for r in range(3):
            for c in range(3):
                rn[r, c] = size2 * sigma_m[r, c]
                s[r, c] = pht[r, c] - m[r] * pht[_SIZE, c] + rn[r, c]
        a00, d11, f22 = s[0, 0], s[1, 1], s[2, 2]
        b01 = 0.5 * (s[0, 1] + s[1, 0])
        c02 = 0.5 * (s[0, 2] + s[2, 0])
        e12 = 0.5 * (s[1, 2] + s[2, 1])
        k00, k01, k02 = d11 * f22 - e12 * e12, c02 * e12 - b01 * f22, b01 * e12 - c02 * d11
        det = a00 * k00 + b01 * k01 + c02 * k02
        if not det > 0.0:
            return 1
        k11, k12, k22 = a00 * f22 - c02 * c02, b01 * c02 - a00 * e12, a00 * d11 - b01 * b01
        i00, i01, i02 = k00 / det, k01 / det, k02 / det
        i11, i12, i22 = k11 / det, k12 / det, k22 / det
        u, v, z = nu[0], nu[1], nu[2]
        maha = (
            u * (i00 * u + i01 * v + i02 * z)
            + v * (i01 * u + i11 * v + i12 * z)
            + z * (i02 * u + i12 * v + i22 * z)
        )
        loglik[j] = -0.5 * (maha + math.log(det) + 3.0 * _LOG_2PI)
        xo = xs_out[j]
        for i in range(_D):
            h0, h1, h2 = pht[i, 0], pht[i, 1], pht[i, 2]
            g0 = h0 * i00 + h1 * i01 + h2 * i02
            g1 = h0 * i01 + h1 * i11 + h2 * i12
            g2 = h0 * i02 + h1 * i12 + h2 * i22
            gain[i, 0], gain[i, 1], gain[i, 2] = g0, g1, g2
            xo[i] = x[i] + (g0 * u + g1 * v + g2 * z)
        for i in range(_D):  # A = (I − KH) P = P − K (P Hᵀ)ᵀ
            for k in range(_D):
                a[i, k] = p[i, k] - (
                    gain[i, 0] * pht[k, 0] + gain[i, 1] * pht[k, 1] + gain[i, 2] * pht[k, 2]
                )
        for i in range(_D):  # W = A Hᵀ − K Rn
            for c in range(3):
                w[i, c] = (a[i, c] - a[i, _SIZE] * m[c]) - (
                    gain[i, 0] * rn[0, c] + gain[i, 1] * rn[1, c] + gain[i, 2] * rn[2, c]
                )
        po = ps_out[j]
        for i in range(_D):  # A − W Kᵀ
            for k in range(_D):
                po[i, k] = a[i, k] - (
                    w[i, 0] * gain[k, 0] + w[i, 1] * gain[k, 1] + w[i, 2] * gain[k, 2]
                )
        _symmetrise(po)
    n = xs.shape[0]
    if n == 1:
        mu_out[:] = mu
        return 0
    # The MMAE probabilities (kernels_track_numpy.mmae_probabilities' float operations, in its
    # order):
    # Bayes' rule in log space, μ_j ∝ μ_j L_j, every μ raised to the floor.
    top = -math.inf
    for j in range(n):
        lp = math.log(mu[j]) + loglik[j] if mu[j] > 0.0 else -math.inf
        mu_out[j] = lp
        top = max(top, lp)
    total = 0.0
    for j in range(n):
        mu_out[j] = math.exp(mu_out[j] - top)
        total += mu_out[j]
    norm = 0.0
    for j in range(n):
        mu_out[j] = max(mu_out[j] / total, floor)
        norm += mu_out[j]
    for j in range(n):
        mu_out[j] = mu_out[j] / norm
    return 0


@_jit(f"void({_M}, {_T}, float64, float64, {_M}, {_T})")
def track_size_update(  # noqa: PLR0917 - numba kernels take positional arguments
    xs: FloatArray,
    ps: FloatArray,
    size: float,
    var: float,
    xs_out: FloatArray,
    ps_out: FloatArray,
) -> None:
    """Scalar Joseph-form update of every model's state on a measured size (``H = e_R``)."""
    gain = np.empty(_D)
    a = np.empty((_D, _D))
    for j in range(xs.shape[0]):
        x = xs[j]
        p = ps[j]
        s = p[_SIZE, _SIZE] + var
        innovation = size - x[_SIZE]
        xo = xs_out[j]
        for i in range(_D):
            gain[i] = p[i, _SIZE] / s
            xo[i] = x[i] + gain[i] * innovation
        for i in range(_D):
            for k in range(_D):
                a[i, k] = p[i, k] - gain[i] * p[_SIZE, k]
        po = ps_out[j]
        for i in range(_D):
            for k in range(_D):
                po[i, k] = a[i, k] - a[i, _SIZE] * gain[k] + var * gain[i] * gain[k]
        _symmetrise(po)


@_jit(f"void({_V}, {_M}, {_T}, int64[::1], {_V})")
def track_combine(
    mu: FloatArray, xs: FloatArray, ps: FloatArray, codes: IntArray, out: FloatArray
) -> None:
    """The probability-weighted state, turn rate, position variances and size into ``out``.

    Slots: :data:`dffd.core.kernel_layout.COMBINE_STATE` … ; the position variance is the
    diagonal of ``Σ μ_j (P_j + d_j d_jᵀ)``, the turn rate ``Σ μ_j ω_j`` (0 for CV, the kinematic
    rate for CA, the state for CT).
    """
    n = xs.shape[0]
    for i in range(9):
        acc = 0.0
        for j in range(n):
            acc += mu[j] * xs[j, i]
        out[COMBINE_STATE + i] = acc
    for i in range(3):
        acc_p = 0.0
        acc_d = 0.0
        for j in range(n):
            d = xs[j, i] - out[COMBINE_STATE + i]
            acc_p += mu[j] * ps[j, i, i]
            acc_d += mu[j] * (d * d)
        out[COMBINE_VAR + i] = acc_p + acc_d
    omega = 0.0
    size = 0.0
    size_var = 0.0
    for j in range(n):
        x = xs[j]
        turn = 0.0
        if codes[j] == MODEL_CT:
            turn = x[_OMEGA]
        elif codes[j] == MODEL_CA:
            vx, vz, ax, az = x[_VX], x[_VZ], x[_AX], x[_AZ]
            speed2 = max(vx * vx + vz * vz, _MIN_TURN_SPEED2)
            turn = (vx * az - vz * ax) / speed2
        omega += mu[j] * turn
        size += mu[j] * x[_SIZE]
        size_var += mu[j] * ps[j, _SIZE, _SIZE]
    out[COMBINE_OMEGA] = omega
    out[COMBINE_SIZE] = size
    out[COMBINE_SIZE_VAR] = size_var


# -- a direction and depth as a world point (dffd.core.tracking3d_camera.cartesian_measurement)
@_jit(f"void({', '.join(['float64'] * 12)}, {_V}, {_M})")
def cartesian_point(  # noqa: PLR0917 - the measurement's fields and the camera's
    u_px: float,
    v_px: float,
    pan_deg: float,
    tilt_deg: float,
    z: float,
    sigma_z_m: float,
    sigma_px: float,
    sigma_angle_deg: float,
    pixel_pitch_mm: float,
    image_distance_mm: float,
    cx: float,
    cy: float,
    world: FloatArray,
    cov: FloatArray,
) -> None:
    """The world point of centroid (``u_px``, ``v_px``) at pan/tilt (degrees) and depth ``z``
    into ``world`` and its covariance (first-order propagation of the σ of the centroid, the
    depth and the angles) into ``cov``: the camera's pixel pitch and image distance (mm) and
    principal point (``cx``, ``cy``). The NumPy twin's float operations in its order, so its
    values bit for bit (~20 µs of Python floats and two array builds a tracking frame)."""
    k = pixel_pitch_mm / image_distance_mm
    du = u_px - cx
    dv = v_px - cy
    q0, q1, q2 = k * du * z, k * dv * z, z  # the camera-frame point
    p, t = math.radians(pan_deg), math.radians(tilt_deg)
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    # rot = R_pan R_tilt, and the derivative matrices d(R_pan)/dp R_tilt and R_pan d(R_tilt)/dt,
    # written out by rows; every dot product summed left to right
    r00, r01, r02 = cp, sp * st, sp * ct
    r10, r11, r12 = 0.0, ct, -st
    r20, r21, r22 = -sp, cp * st, cp * ct
    p00, p01, p02 = -sp, cp * st, cp * ct
    p10, p11, p12 = 0.0, 0.0, 0.0
    p20, p21, p22 = -cp, -sp * st, -sp * ct
    t00, t01, t02 = 0.0, sp * ct, -sp * st
    t10, t11, t12 = 0.0, -st, -ct
    t20, t21, t22 = 0.0, cp * ct, -cp * st
    world[0] = r00 * q0 + r01 * q1 + r02 * q2
    world[1] = r10 * q0 + r11 * q1 + r12 * q2
    world[2] = r20 * q0 + r21 * q1 + r22 * q2
    # the Jacobian with respect to (u, v, z, pan, tilt), one row per world axis
    kz = k * z
    u0, u1 = k * du, k * dv  # the unit-depth point (u0, u1, 1)
    a0, a1, a2 = r00 * kz, r01 * kz, r00 * u0 + r01 * u1 + r02 * 1.0
    a3, a4 = p00 * q0 + p01 * q1 + p02 * q2, t00 * q0 + t01 * q1 + t02 * q2
    b0, b1, b2 = r10 * kz, r11 * kz, r10 * u0 + r11 * u1 + r12 * 1.0
    b3, b4 = p10 * q0 + p11 * q1 + p12 * q2, t10 * q0 + t11 * q1 + t12 * q2
    c0, c1, c2 = r20 * kz, r21 * kz, r20 * u0 + r21 * u1 + r22 * 1.0
    c3, c4 = p20 * q0 + p21 * q1 + p22 * q2, t20 * q0 + t21 * q1 + t22 * q2
    sa = math.radians(sigma_angle_deg)
    v0, v1, v2 = sigma_px * sigma_px, sigma_px * sigma_px, sigma_z_m * sigma_z_m
    v3, v4 = sa * sa, sa * sa
    # J diag(var) Jᵀ: symmetric as computed (each entry one sum of the five terms)
    wa0, wa1, wa2, wa3, wa4 = a0 * v0, a1 * v1, a2 * v2, a3 * v3, a4 * v4
    wb0, wb1, wb2, wb3, wb4 = b0 * v0, b1 * v1, b2 * v2, b3 * v3, b4 * v4
    aa = wa0 * a0 + wa1 * a1 + wa2 * a2 + wa3 * a3 + wa4 * a4
    ab = wa0 * b0 + wa1 * b1 + wa2 * b2 + wa3 * b3 + wa4 * b4
    ac = wa0 * c0 + wa1 * c1 + wa2 * c2 + wa3 * c3 + wa4 * c4
    bb = wb0 * b0 + wb1 * b1 + wb2 * b2 + wb3 * b3 + wb4 * b4
    bc = wb0 * c0 + wb1 * c1 + wb2 * c2 + wb3 * c3 + wb4 * c4
    cc = c0 * v0 * c0 + c1 * v1 * c1 + c2 * v2 * c2 + c3 * v3 * c3 + c4 * v4 * c4
    cov[0, 0], cov[0, 1], cov[0, 2] = aa, ab, ac
    cov[1, 0], cov[1, 1], cov[1, 2] = ab, bb, bc
    cov[2, 0], cov[2, 1], cov[2, 2] = ac, bc, cc
