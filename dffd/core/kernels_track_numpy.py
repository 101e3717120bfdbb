"""NumPy twins of the 3D tracker's compiled kernels (:mod:`dffd.core.kernels_track`).

Same names, signatures and results (to rounding) as the compiled kernels, written as the bank's
stacked NumPy products; they run while numba compiles (:mod:`dffd.core.kernel_dispatch`), and
:func:`predict_models` also predicts a bank of models the kernels have no code for.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from dffd.core.kernel_layout import (
    COMBINE_OMEGA,
    COMBINE_SIZE,
    COMBINE_SIZE_VAR,
    COMBINE_STATE,
    COMBINE_VAR,
    MODEL_CA,
    MODEL_CT,
    MODEL_CV,
)
from dffd.core.motion_models import (
    POS,
    STATE_DIM,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    MotionModel,
)

__all__ = [
    "cartesian_point",
    "inv3_loglik_stack",
    "mmae_probabilities",
    "predict_models",
    "size_update",
    "sym_stack",
    "track_combine",
    "track_predict",
    "track_size_update",
    "track_unit_update",
    "unit_update_all",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

SIZE = STATE_DIM  # the size state R follows the models' 10 elements
TRACK_DIM = STATE_DIM + 1
_LOG_2PI = math.log(2.0 * math.pi)
_POS_IDX = np.arange(3)  # the position's indices in the state (diagonal gathers)


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
    """The world point and its covariance into ``world`` and ``cov``
    (:func:`dffd.core.kernels_track.cartesian_point`, the same float operations)."""
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


def track_predict(  # noqa: PLR0917 - the compiled kernels' positional signature
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
    """Every model's prediction over ``dt`` (see :func:`predict_models`)."""
    models = [
        _model(int(c), float(qj), float(qo))
        for c, qj, qo in zip(codes.tolist(), q.tolist(), q_omega.tolist(), strict=True)
    ]
    predict_models(models, xs, ps, dt, q_size, xs_out, ps_out)


def track_unit_update(  # noqa: PLR0917 - the compiled kernels' positional signature
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
    """:func:`unit_update_all` into the outputs and the models' probabilities after it
    (:func:`mmae_probabilities`; ``mu`` for a bank of one); 1 when an innovation covariance is
    not positive definite, else 0."""
    try:
        x_new, p_new, ll = unit_update_all(xs, ps, m, sigma_m)
    except np.linalg.LinAlgError:
        return 1
    xs_out[:] = x_new
    ps_out[:] = p_new
    loglik[:] = ll
    mu_out[:] = mmae_probabilities(mu, ll, floor) if len(mu) > 1 else mu
    return 0


def mmae_probabilities(prior: FloatArray, log_likelihoods: FloatArray, floor: float) -> FloatArray:
    """Bayes' rule in log space, ``μ_j ∝ μ_j L_j``, then every μ raised to ``floor``."""
    # A handful of models: plain floats (NumPy's per-call cost dominates at this size).
    log_post = [
        math.log(p) + ll if p > 0.0 else -math.inf
        for p, ll in zip(prior.tolist(), log_likelihoods.tolist(), strict=True)
    ]
    top = max(log_post)
    post = [math.exp(v - top) for v in log_post]
    total = sum(post)
    post = [max(v / total, floor) for v in post]
    return np.asarray(post, dtype=np.float64) / sum(post)


def track_size_update(  # noqa: PLR0917 - the compiled kernels' positional signature
    xs: FloatArray,
    ps: FloatArray,
    size: float,
    var: float,
    xs_out: FloatArray,
    ps_out: FloatArray,
) -> None:
    """:func:`size_update` into the outputs."""
    x_new, p_new = size_update(xs, ps, size, var)
    xs_out[:] = x_new
    ps_out[:] = p_new


def track_combine(
    mu: FloatArray, xs: FloatArray, ps: FloatArray, codes: IntArray, out: FloatArray
) -> None:
    """The probability-weighted state, turn rate, position variances and size into ``out``."""
    x = mu @ xs
    d = xs[:, POS] - x[POS]
    var = mu @ ps[:, _POS_IDX, _POS_IDX] + mu @ (d * d)
    omega = 0.0
    for m, code, xi in zip(mu.tolist(), codes.tolist(), xs, strict=True):
        omega += m * _model(code, 0.0, 0.0).angular_speed(xi[:STATE_DIM])
    out[COMBINE_STATE : COMBINE_STATE + 9] = x[:9]
    out[COMBINE_OMEGA] = omega
    out[COMBINE_VAR : COMBINE_VAR + 3] = var
    out[COMBINE_SIZE] = float(mu @ xs[:, SIZE])
    out[COMBINE_SIZE_VAR] = float(mu @ ps[:, SIZE, SIZE])


def predict_models(  # noqa: PLR0917 - the kernels' arrays
    models: Sequence[MotionModel],
    xs: FloatArray,
    ps: FloatArray,
    dt: float,
    q_size: float,
    xs_out: FloatArray,
    ps_out: FloatArray,
) -> None:
    """Every model's ``predict`` over ``dt``, the size carried (``Q_RR = q_size dt``), and
    ``P⁻ = sym(F P Fᵀ + Q)`` in one stacked product for all models."""
    n_models = len(models)
    fs = np.zeros((n_models, TRACK_DIM, TRACK_DIM))
    qs = np.zeros((n_models, TRACK_DIM, TRACK_DIM))
    fs[:, SIZE, SIZE] = 1.0
    n = STATE_DIM
    for j, model in enumerate(models):
        xs_out[j, :n], fs[j, :n, :n], qs[j, :n, :n] = model.predict(xs[j, :n], dt)
    xs_out[:, SIZE] = xs[:, SIZE]
    qs[:, SIZE, SIZE] = q_size * dt
    new_p = fs @ ps @ fs.transpose(0, 2, 1)
    new_p += qs
    ps_out[:] = sym_stack(new_p)


def unit_update_all(
    xs: FloatArray, ps: FloatArray, m: FloatArray, sigma_m: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The Joseph-form update on the pseudo-measurement ``0 = p − R m`` (``H = [I₃ 0 … −m]``,
    noise ``R̂² Σ_m``) of every model at once on stacked (n, d) states and (n, d, d)
    covariances; returns (x⁺, P⁺, log-likelihoods)."""
    size = xs[:, SIZE]
    nu = size[:, None] * m - xs[:, POS]  # (n, 3)
    pht = ps[:, :, POS] - ps[:, :, SIZE, None] * m  # (n, d, 3) = P Hᵀ
    rn = (size * size)[:, None, None] * sigma_m  # (n, 3, 3)
    s = pht[:, POS, :] - m[:, None] * pht[:, SIZE, None, :] + rn
    s_inv, loglik = inv3_loglik_stack(s, nu)
    gain = pht @ s_inv  # (n, d, 3)
    xs_new = xs + (gain @ nu[:, :, None])[:, :, 0]
    gt = gain.transpose(0, 2, 1)
    a = ps - gain @ pht.transpose(0, 2, 1)  # (I − KH) P
    aht = a[:, :, POS] - a[:, :, SIZE, None] * m  # A Hᵀ
    # A − A Hᵀ Kᵀ + K Rn Kᵀ, with the two products sharing Kᵀ.
    ps_new = a - (aht - gain @ rn) @ gt
    return xs_new, sym_stack(ps_new), loglik


def size_update(
    xs: FloatArray, ps: FloatArray, size: float, var: float
) -> tuple[FloatArray, FloatArray]:
    """Scalar Joseph-form update of every model's state on a measured size (``H = e_R``)."""
    s = ps[:, SIZE, SIZE] + var  # (n,)
    gain = ps[:, :, SIZE] / s[:, None]  # (n, d)
    xs_new = xs + gain * (size - xs[:, SIZE])[:, None]
    a = ps - gain[:, :, None] * ps[:, None, SIZE, :]
    ps_new = a - a[:, :, SIZE, None] * gain[:, None, :] + var * gain[:, :, None] * gain[:, None, :]
    return xs_new, 0.5 * (ps_new + ps_new.transpose(0, 2, 1))


def inv3_loglik_stack(s: FloatArray, nu: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Inverses of a (n, 3, 3) stack of innovation covariances (symmetrised first, by
    cofactors) and the Gaussian log-likelihoods of the (n, 3) innovations: a few models, in
    floats, where ``np.linalg`` and ``einsum`` cost more per call than the work."""
    invs: list[list[list[float]]] = []
    logliks: list[float] = []
    for ((a, b0, c0), (b1, d, e0), (c1, e1, f)), (u, v, w) in zip(
        s.tolist(), nu.tolist(), strict=True
    ):
        # 0.5 (S + Sᵀ) element by element, as the per-model update symmetrises.
        b, c, e = 0.5 * (b0 + b1), 0.5 * (c0 + c1), 0.5 * (e0 + e1)
        c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
        det = a * c00 + b * c01 + c * c02
        if not det > 0.0:
            raise np.linalg.LinAlgError(f"innovation covariance is not positive definite: {s!r}")
        c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
        i00, i01, i02 = c00 / det, c01 / det, c02 / det
        i11, i12, i22 = c11 / det, c12 / det, c22 / det
        invs.append([[i00, i01, i02], [i01, i11, i12], [i02, i12, i22]])
        maha = (
            u * (i00 * u + i01 * v + i02 * w)
            + v * (i01 * u + i11 * v + i12 * w)
            + w * (i02 * u + i12 * v + i22 * w)
        )
        logliks.append(-0.5 * (maha + math.log(det) + 3.0 * _LOG_2PI))
    return np.array(invs), np.array(logliks)


def sym_stack(m: FloatArray) -> FloatArray:
    """``(M + Mᵀ)/2`` of every matrix of a (n, d, d) stack."""
    out = m + m.transpose(0, 2, 1)
    out *= 0.5
    return out


@functools.cache
def _model(code: int, q: float, q_omega: float) -> MotionModel:
    """The bank's model of ``code`` (cached: the twins build none per call)."""
    if code == MODEL_CV:
        return ConstantVelocity(q)
    if code == MODEL_CA:
        return ConstantAcceleration(q)
    if code == MODEL_CT:
        return CoordinatedTurn(q, q_omega)
    raise ValueError(f"unknown motion-model code {code}")
