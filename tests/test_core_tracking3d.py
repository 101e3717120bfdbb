"""3D tracker: exact discretisation of each motion model, the model-probability update, IMM
mixing, the measurement conversion, and end-to-end runs on synthetic trajectories."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from dffd.core.geometry import camera_point, image_shift, to_world, world_rotation
from dffd.core.kernels_track_numpy import size_update as _size_update
from dffd.core.kernels_track_numpy import unit_update_all as _unit_update_all
from dffd.core.motion_models import (
    STATE_DIM,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    kinematic_turn_rate,
)
from dffd.core.track_feed import FeedFrame, SizeFeed
from dffd.core.tracking3d import (
    Tracker3D,
    _unit_update,
    imm_mix,
    markov_matrix,
    mmae_probabilities,
)
from dffd.core.tracking3d_camera import (
    CameraModel,
    DirectionDepth,
    DirectionSize,
    cartesian_measurement,
    direction_rate_deg_s,
    unit_size_point,
)
from dffd.core.tracking3d_types import (
    SIZE,
    TRACK_DIM,
    TRACKER_KINDS,
    Track3DEstimate,
    Tracker3DConfig,
)

FloatArray = np.ndarray
DTS = (1e-3, 1 / 30, 0.1, 0.7)


def van_loan(a: FloatArray, gqg: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """(exp(A dt), ∫ exp(Aτ) G Qc Gᵀ exp(Aτ)ᵀ dτ) by Van Loan's block exponential."""
    n = a.shape[0]
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -a
    m[:n, n:] = gqg
    m[n:, n:] = a.T
    e = expm(m * dt)
    phi = e[n:, n:].T
    return phi, phi @ e[:n, n:]


def per_axis_continuous(order: int, q: float) -> tuple[FloatArray, FloatArray]:
    """Continuous (A, G Qc Gᵀ) on the 9 kinematic states for an integrator chain of ``order``."""
    block = np.zeros((3, 3))
    for i in range(order - 1):
        block[i, i + 1] = 1.0
    noise = np.zeros((3, 3))
    noise[order - 1, order - 1] = q
    return np.kron(block, np.eye(3)), np.kron(noise, np.eye(3))


# -- exact discretisation ---------------------------------------------------------------------


@pytest.mark.parametrize("dt", DTS)
def test_constant_velocity_is_the_exact_discretisation(dt: float) -> None:
    q = 0.03
    a, gqg = per_axis_continuous(2, q)
    phi, qd = van_loan(a, gqg, dt)
    x = np.arange(STATE_DIM) * 0.1 + 0.2
    xp, f, qm = ConstantVelocity(q).predict(x, dt)
    np.testing.assert_allclose(f[:6, :6], phi[:6, :6], atol=1e-12)
    np.testing.assert_allclose(qm[:9, :9], qd, rtol=1e-9, atol=1e-15)
    # closed form: p + v dt, v kept, a reset to 0 (the model has none), ω carried untouched
    np.testing.assert_allclose(xp[:3], x[:3] + x[3:6] * dt)
    np.testing.assert_allclose(xp[3:6], x[3:6])
    assert np.all(xp[6:9] == 0.0)
    assert xp[9] == x[9]
    assert qm[9, 9] == 0.0


@pytest.mark.parametrize("dt", DTS)
def test_constant_acceleration_is_the_exact_discretisation(dt: float) -> None:
    q = 0.2
    a, gqg = per_axis_continuous(3, q)
    phi, qd = van_loan(a, gqg, dt)
    x = np.arange(STATE_DIM) * 0.1 - 0.3
    xp, f, qm = ConstantAcceleration(q).predict(x, dt)
    np.testing.assert_allclose(f[:9, :9], phi, atol=1e-12)
    np.testing.assert_allclose(qm[:9, :9], qd, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(xp[:3], x[:3] + x[3:6] * dt + x[6:9] * dt * dt / 2)
    np.testing.assert_allclose(qm[0, 0], q * dt**5 / 20)  # the textbook closed form


def _turn_rhs(_t: float, s: FloatArray) -> FloatArray:
    """Continuous coordinated turn on (px, py, pz, vx, vy, vz, ω): v̇_h = ω J v_h."""
    vx, vy, vz, w = s[3], s[4], s[5], s[6]
    return np.array([vx, vy, vz, -w * vz, 0.0, w * vx, 0.0])


@pytest.mark.parametrize("omega", [0.0, 1e-6, 3e-3, 0.25, -0.8, 2.5])
@pytest.mark.parametrize("dt", [1 / 30, 0.5])
def test_coordinated_turn_mean_matches_integration_of_the_continuous_model(
    omega: float, dt: float
) -> None:
    x = np.array([1.0, -0.2, 5.0, 0.3, 0.05, -0.4, 9.0, 9.0, 9.0, omega])
    xp, _, _ = CoordinatedTurn(0.01, 0.001).predict(x, dt)
    s0 = np.array([*x[:6], omega])
    sol = solve_ivp(_turn_rhs, (0.0, dt), s0, rtol=1e-12, atol=1e-14)
    end = sol.y[:, -1]
    np.testing.assert_allclose(xp[:6], end[:6], atol=1e-10)
    # the acceleration is the turn's output ω J v at the end of the step; vertical none
    np.testing.assert_allclose(xp[6], -omega * xp[5], atol=1e-14)
    np.testing.assert_allclose(xp[8], omega * xp[3], atol=1e-14)
    assert xp[7] == 0.0
    assert xp[9] == omega


def test_coordinated_turn_quarter_turn_closed_form() -> None:
    # moving at +x with ω = π/2 per second for 1 s: a quarter circle of radius v/ω to the left
    # of the motion seen from above (towards +z), ending with velocity +z
    v, w = 0.5, math.pi / 2
    x = np.zeros(STATE_DIM)
    x[3], x[9] = v, w
    xp, _, _ = CoordinatedTurn(0.0, 0.0).predict(x, 1.0)
    r = v / w
    np.testing.assert_allclose(xp[[0, 2]], [r, r], atol=1e-14)
    np.testing.assert_allclose(xp[[3, 5]], [0.0, v], atol=1e-14)
    assert CoordinatedTurn(0.0, 0.0).angular_speed(xp) == w
    assert kinematic_turn_rate(xp[3:6], xp[6:9]) == pytest.approx(w)


@pytest.mark.parametrize("omega", [0.0, 4e-3, 0.3, -1.7])
def test_coordinated_turn_jacobian_matches_finite_differences(omega: float) -> None:
    model = CoordinatedTurn(0.01, 0.001)
    x = np.array([1.0, -0.2, 5.0, 0.3, 0.05, -0.4, 0.0, 0.0, 0.0, omega])
    dt = 0.2
    _, f, _ = model.predict(x, dt)
    h = 1e-6
    num = np.zeros((STATE_DIM, STATE_DIM))
    for k in range(STATE_DIM):
        e = np.zeros(STATE_DIM)
        e[k] = h
        num[:, k] = (model.predict(x + e, dt)[0] - model.predict(x - e, dt)[0]) / (2 * h)
    np.testing.assert_allclose(f, num, atol=1e-8)


@pytest.mark.parametrize("omega", [0.0, 1e-5, 2e-3, 0.4, -1.1, 3.0])
@pytest.mark.parametrize("dt", DTS)
def test_coordinated_turn_noise_is_exact_at_the_current_turn_rate(omega: float, dt: float) -> None:
    q = 0.05
    # continuous linear model at fixed ω on (px, pz, vx, vz, py, vy)
    a = np.zeros((6, 6))
    a[0, 2] = a[1, 3] = a[4, 5] = 1.0
    a[2, 3], a[3, 2] = -omega, omega
    gqg = np.zeros((6, 6))
    gqg[2, 2] = gqg[3, 3] = gqg[5, 5] = q
    phi, qd = van_loan(a, gqg, dt)
    x = np.array([1.0, -0.2, 5.0, 0.3, 0.05, -0.4, 0.0, 0.0, 0.0, omega])
    _, f, qm = CoordinatedTurn(q, 0.0).predict(x, dt)
    idx = [0, 2, 3, 5, 1, 4]  # px, pz, vx, vz, py, vy in the tracker's state
    np.testing.assert_allclose(f[np.ix_(idx, idx)], phi, atol=1e-12)
    scale = float(np.max(np.abs(qd)))
    np.testing.assert_allclose(qm[np.ix_(idx, idx)], qd, atol=1e-9 * scale)
    # a_h = ω J v_h: its noise is the velocity noise mapped by ω J
    lift = np.zeros((8, 6))
    lift[:6, :] = np.eye(6)
    lift[6, 3], lift[7, 2] = -omega, omega  # ax = −ω vz, az = ω vx
    full = lift @ qd @ lift.T
    idx_a = [*idx, 6, 8]
    np.testing.assert_allclose(qm[np.ix_(idx_a, idx_a)], full, atol=1e-9 * scale)
    assert np.allclose(qm, qm.T)
    assert np.min(np.linalg.eigvalsh(qm)) > -1e-12 * scale


# -- measurement conversion -------------------------------------------------------------------

CAM = CameraModel.centred((640, 480), 0.005, 31.0)


def test_cartesian_measurement_matches_geometry_and_its_jacobian() -> None:
    meas = DirectionDepth((400.0, 150.0), 12.0, -5.0, 6.0, 0.03, 0.4, 0.02)
    y, r = cartesian_measurement(meas, CAM)
    expected = to_world(camera_point((400.0, 150.0), 6.0, (640, 480), 0.005, 31.0), 12.0, -5.0)
    np.testing.assert_allclose(y, expected, atol=1e-12)

    def point(u: float, v: float, z: float, pan: float, tilt: float) -> FloatArray:
        return np.array(to_world(camera_point((u, v), z, (640, 480), 0.005, 31.0), pan, tilt))

    base = [400.0, 150.0, 6.0, 12.0, -5.0]
    steps = [1e-3, 1e-3, 1e-6, 1e-5, 1e-5]
    jac = np.zeros((3, 5))
    for k in range(5):
        hi, lo = list(base), list(base)
        hi[k] += steps[k]
        lo[k] -= steps[k]
        jac[:, k] = (point(*hi) - point(*lo)) / (2 * steps[k])
    sa = 0.02  # degrees: the finite differences above are per degree
    var = np.array([0.4**2, 0.4**2, 0.03**2, sa**2, sa**2])
    np.testing.assert_allclose(r, (jac * var) @ jac.T, rtol=1e-6, atol=1e-14)
    # elongated along the line of sight: the depth σ dominates
    eig, vec = np.linalg.eigh(r)
    sight = expected / np.linalg.norm(expected)
    assert abs(float(vec[:, -1] @ sight)) > 0.99
    assert eig[-1] > 100 * eig[-2]


# -- model probabilities and mixing -----------------------------------------------------------


def test_mmae_probability_update_by_hand() -> None:
    prior = np.array([0.5, 0.3, 0.2])
    lik = np.array([0.1, 0.4, 0.001])
    # μ L = [0.05, 0.12, 0.0002], sum 0.1702 → [0.293772, 0.705053, 0.001175]
    post = mmae_probabilities(prior, np.log(lik), floor=0.0)
    np.testing.assert_allclose(post, [0.05 / 0.1702, 0.12 / 0.1702, 0.0002 / 0.1702])
    # floor 0.01: the third is raised to 0.01, then all renormalised by 1.008825
    floored = mmae_probabilities(prior, np.log(lik), floor=0.01)
    raw = np.array([0.05 / 0.1702, 0.12 / 0.1702, 0.01])
    np.testing.assert_allclose(floored, raw / raw.sum())
    assert floored.sum() == pytest.approx(1.0)


def test_mmae_probabilities_survive_extreme_likelihoods() -> None:
    # log-likelihoods far below exp's range: still finite, the best model wins, none dies
    post = mmae_probabilities(np.full(3, 1 / 3), np.array([-1e5, -1e5 - 50.0, -3e5]), 1e-3)
    assert np.all(np.isfinite(post))
    assert post[0] == pytest.approx(1 - 2e-3, abs=1e-5)
    assert np.all(post >= 1e-3 / (1 + 2e-3))


def test_compiled_mmae_probabilities_are_the_python_ones_bit_for_bit() -> None:
    # the unit-size update kernel computes the probabilities after its update (one call a
    # frame): the same float operations in the same order as mmae_probabilities
    from dffd.core import kernels_track

    rng = np.random.default_rng(3)
    d = 11
    for k in range(200):
        xs = rng.normal(0.0, 1.0, (3, d))
        xs[:, d - 1] = rng.uniform(0.02, 0.05, 3)  # the size R
        a = rng.normal(0.0, 0.3, (3, d, d))
        ps = np.ascontiguousarray(a @ a.transpose(0, 2, 1) + 1e-2 * np.eye(d))
        m = rng.normal(0.0, 30.0, 3)
        b = rng.normal(0.0, 1.0, (3, 3))
        sigma_m = np.ascontiguousarray(b @ b.T + np.eye(3))
        mu = rng.dirichlet(np.ones(3))
        if k % 7 == 0:
            mu[k % 3] = 0.0  # a dead model: log μ = −∞
        xs_out, ps_out = np.empty_like(xs), np.empty_like(ps)
        loglik, mu_out = np.empty(3), np.empty(3)
        status = kernels_track.track_unit_update(
            xs, ps, m, sigma_m, mu, 1e-3, xs_out, ps_out, loglik, mu_out
        )
        assert status == 0
        assert mu_out.tolist() == mmae_probabilities(mu, loglik, 1e-3).tolist()


def test_markov_matrix_is_the_exact_chain_transition() -> None:
    rate, n = 0.3, 3
    gen = rate / (n - 1) * (np.ones((n, n)) - n * np.eye(n))
    for dt in (0.0, 1 / 30, 2.0):
        np.testing.assert_allclose(markov_matrix(n, rate, dt), expm(gen * dt), atol=1e-14)
    p = markov_matrix(n, rate, 0.05)
    np.testing.assert_allclose(p.sum(axis=1), 1.0)
    np.testing.assert_allclose(p @ markov_matrix(n, rate, 0.1), markov_matrix(n, rate, 0.15))
    np.testing.assert_allclose(markov_matrix(n, rate, 1e6), np.full((n, n), 1 / n))


def test_imm_mixing_by_hand() -> None:
    mu = np.array([0.8, 0.2])
    pi = np.array([[0.9, 0.1], [0.2, 0.8]])
    x0, x1 = np.zeros(STATE_DIM), np.zeros(STATE_DIM)
    x1[0] = 3.0
    p0, p1 = np.eye(STATE_DIM) * 1.0, np.eye(STATE_DIM) * 4.0
    xs, ps, c = imm_mix(np.stack([x0, x1]), np.stack([p0, p1]), mu, pi)
    # c = πᵀ μ = [0.72 + 0.04, 0.08 + 0.16]
    np.testing.assert_allclose(c, [0.76, 0.24])
    # into model 1: weights [0.08, 0.16]/0.24 = [1/3, 2/3] → mean 2, variance
    # 1/3·(1 + 2²) + 2/3·(4 + 1²) = 5 on the differing axis, 1/3·1 + 2/3·4 = 3 elsewhere
    assert xs[1][0] == pytest.approx(2.0)
    assert ps[1][0, 0] == pytest.approx(5.0)
    assert ps[1][1, 1] == pytest.approx(3.0)
    # into model 0: weights [0.72, 0.04]/0.76
    w1 = 0.04 / 0.76
    assert xs[0][0] == pytest.approx(3.0 * w1)
    m = 3.0 * w1
    assert ps[0][0, 0] == pytest.approx((1 - w1) * (1 + m * m) + w1 * (4 + (3 - m) ** 2))


# -- end to end on synthetic trajectories -----------------------------------------------------


@dataclass(frozen=True)
class Truth:
    t: float
    p: FloatArray
    v: FloatArray
    a: FloatArray
    w: float


Path = Callable[[float], tuple[FloatArray, FloatArray, FloatArray, float]]


def circle_path(t: float) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Radius 2 m around (0, 0.3, 5) at 0.4 m/s: ω = +0.2 rad/s (counter-clockwise from above)."""
    r, v = 2.0, 0.4
    w = v / r
    ph = w * t
    c, s = math.cos(ph), math.sin(ph)
    p = np.array([r * s, 0.3, 5.0 - r * c])
    return p, v * np.array([c, 0.0, s]), v * w * np.array([-s, 0.0, c]), w


def line_path(t: float) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Across the view and away, 0.4 m/s."""
    d = np.array([1.0, 0.0, 0.5]) / math.sqrt(1.25)
    return np.array([-3.0, 0.2, 4.0]) + d * 0.4 * t, d * 0.4, np.zeros(3), 0.0


def stop_and_go_path(t: float) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """2 m legs back and forth, 5 s each with a sin² speed profile, 3 s rests."""
    d = np.array([1.0, 0.0, 0.3]) / math.sqrt(1.09)
    length, go, stop = 2.0, 5.0, 3.0
    k, tau = divmod(t, go + stop)
    sign, base = (1.0, 0.0) if int(k) % 2 == 0 else (-1.0, length)
    if tau < go:
        w = 2 * math.pi / go
        s = length * (tau / go - math.sin(w * tau) / (2 * math.pi))
        ds = length / go * (1 - math.cos(w * tau))
        dds = length / go * w * math.sin(w * tau)
    else:
        s, ds, dds = length, 0.0, 0.0
    p0 = np.array([-2.0, 0.0, 5.0])
    return p0 + d * (base + sign * s), d * sign * ds, d * sign * dds, 0.0


def simulate(
    path: Path, duration_s: float, seed: int, fps: float = 30.0
) -> tuple[list[Truth], dict[str, list[Track3DEstimate]]]:
    """Camera following the target 0.15 s late; seeded centroid, pan/tilt and depth noise."""
    rng = np.random.default_rng(seed)
    trackers = {kind: Tracker3D.of_kind(kind) for kind in TRACKER_KINDS}
    out: dict[str, list[Track3DEstimate]] = {kind: [] for kind in trackers}
    truth: list[Truth] = []
    k = CAM.pixel_pitch_mm / CAM.image_distance_mm
    sigma_px, sigma_deg = 0.3, 0.03
    for i in range(int(duration_s * fps)):
        t = i / fps + rng.uniform(-2e-3, 2e-3)  # frame times jitter: dt varies
        p, v, a, w = path(t)
        aim = path(max(t - 0.15, 0.0))[0]
        pan = math.degrees(math.atan2(aim[0], aim[2]))
        tilt = math.degrees(math.atan2(-aim[1], math.hypot(aim[0], aim[2])))
        cam = world_rotation(pan, tilt).T @ p
        u = CAM.principal_point_px[0] + cam[0] / cam[2] / k + rng.normal(0.0, sigma_px)
        vv = CAM.principal_point_px[1] + cam[1] / cam[2] / k + rng.normal(0.0, sigma_px)
        sigma_z = 0.005 * cam[2]
        meas = DirectionDepth(
            (u, vv),
            pan + rng.normal(0.0, sigma_deg),
            tilt + rng.normal(0.0, sigma_deg),
            cam[2] + rng.normal(0.0, sigma_z),
            sigma_z,
            sigma_px,
            sigma_deg,
        )
        for kind, tracker in trackers.items():
            est = tracker.step(t, meas, CAM)
            assert est is not None
            out[kind].append(est)
        truth.append(Truth(t, p, v, a, w))
    return truth, out


def position_rms(truth: list[Truth], est: list[Track3DEstimate], settle_s: float) -> float:
    err = [
        np.subtract(e.position_m, tr.p)
        for tr, e in zip(truth, est, strict=True)
        if tr.t >= settle_s
    ]
    return float(np.sqrt(np.mean(np.sum(np.square(err), axis=1))))


@pytest.fixture(scope="module")
def circle_run() -> tuple[list[Truth], dict[str, list[Track3DEstimate]]]:
    return simulate(circle_path, 40.0, seed=11)


@pytest.fixture(scope="module")
def stop_and_go_run() -> tuple[list[Truth], dict[str, list[Track3DEstimate]]]:
    return simulate(stop_and_go_path, 32.0, seed=12)


def test_circle_turn_rate_within_five_percent(
    circle_run: tuple[list[Truth], dict[str, list[Track3DEstimate]]],
) -> None:
    truth, out = circle_run
    settle = 15.0
    w_true = truth[0].w
    w = np.array(
        [e.angular_speed_rad_s for tr, e in zip(truth, out["mmae"], strict=True) if tr.t >= settle]
    )
    assert abs(float(np.mean(w)) - w_true) < 0.05 * w_true
    # and not only on average: most frames within 10 %
    assert np.mean(np.abs(w - w_true) < 0.1 * w_true) > 0.8
    final = out["mmae"][-1].model_probabilities
    assert max(final, key=lambda k: final[k]) == "ct"


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_multiple_models_beat_constant_velocity_on_a_circle(
    circle_run: tuple[list[Truth], dict[str, list[Track3DEstimate]]], kind: str
) -> None:
    truth, out = circle_run
    assert position_rms(truth, out[kind], 10.0) < 0.9 * position_rms(truth, out["cv"], 10.0)


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_multiple_models_beat_constant_velocity_on_stop_and_go(
    stop_and_go_run: tuple[list[Truth], dict[str, list[Track3DEstimate]]], kind: str
) -> None:
    truth, out = stop_and_go_run
    assert position_rms(truth, out[kind], 4.0) < position_rms(truth, out["cv"], 4.0)
    # the acceleration is tracked: far better than CV's (which has none)
    acc_err = [
        np.subtract(e.acceleration_m_s2, tr.a)
        for tr, e in zip(truth, out[kind], strict=True)
        if tr.t >= 4
    ]
    acc_true = [tr.a for tr in truth if tr.t >= 4]
    rms = float(np.sqrt(np.mean(np.sum(np.square(acc_err), axis=1))))
    assert rms < 0.6 * float(np.sqrt(np.mean(np.sum(np.square(acc_true), axis=1))))


def test_line_is_tracked_as_constant_velocity_without_turning() -> None:
    truth, out = simulate(line_path, 15.0, seed=13)
    est = out["mmae"]
    final = est[-1].model_probabilities
    assert max(final, key=lambda k: final[k]) == "cv"
    late = [(tr, e) for tr, e in zip(truth, est, strict=True) if tr.t >= 5.0]
    assert max(abs(e.angular_speed_rad_s) for _, e in late) < 0.02
    v_err = [np.linalg.norm(np.subtract(e.velocity_m_s, tr.v)) for tr, e in late]
    assert float(np.sqrt(np.mean(np.square(v_err)))) < 0.02
    # published σ honest: about 95 % of position errors inside 2σ per axis
    inside = [
        np.all(np.abs(np.subtract(e.position_m, tr.p)) <= 2 * np.array(e.position_sigma_m))
        for tr, e in late
    ]
    assert 0.8 < float(np.mean(inside)) <= 1.0


def test_tracker_is_deterministic_and_restarts_after_a_gap() -> None:
    meas = DirectionDepth((320.0, 240.0), 5.0, 1.0, 4.0, 0.02)
    a, b = Tracker3D.of_kind("imm"), Tracker3D.of_kind("imm")
    for i in range(20):
        ea, eb = a.step(i / 30, meas, CAM), b.step(i / 30, meas, CAM)
        assert ea == eb
    assert a.step(1.0, None) is not None  # predict only
    fresh = a.step(5.0, meas, CAM)  # 4 s without a measurement: a new track
    assert fresh is not None
    assert fresh.velocity_m_s == (0.0, 0.0, 0.0)
    assert list(fresh.model_probabilities.values()) == pytest.approx([1 / 3] * 3)
    empty = Tracker3D.of_kind("cv")
    assert empty.step(0.0, None) is None
    with pytest.raises(ValueError, match="camera model"):
        empty.step(0.0, meas)


# -- size-state measurements (direction and image size; burst sizes) --------------------------


def _generic_update(
    x: FloatArray, p: FloatArray, h: FloatArray, y: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Textbook Kalman update with an explicit H (the reference for the structured ones)."""
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    nu = y - h @ x
    ikh = np.eye(len(x)) - k @ h
    p_new = ikh @ p @ ikh.T + k @ r @ k.T
    _, logdet = np.linalg.slogdet(s)
    loglik = -0.5 * (nu @ np.linalg.solve(s, nu) + logdet + len(y) * math.log(2 * math.pi))
    return x + k @ nu, p_new, float(loglik)


def _random_state(seed: int) -> tuple[FloatArray, FloatArray]:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=TRACK_DIM)
    x[SIZE] = 0.036
    a = rng.normal(size=(TRACK_DIM, TRACK_DIM)) * 0.1
    return x, a @ a.T + np.eye(TRACK_DIM) * 1e-3


def test_unit_size_update_is_the_kalman_update_of_p_minus_r_m() -> None:
    x, p = _random_state(3)
    m = np.array([10.0, -2.0, 150.0])
    sigma_m = np.diag([4.0, 3.0, 900.0]) * 1e-2
    h = np.zeros((3, TRACK_DIM))
    h[:, :3] = np.eye(3)
    h[:, SIZE] = -m
    ref = _generic_update(x, p, h, np.zeros(3), x[SIZE] ** 2 * sigma_m)
    got = _unit_update(x, p, m, sigma_m)
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got[1], ref[1], rtol=1e-8, atol=1e-12)
    assert got[2] == pytest.approx(ref[2], rel=1e-9)


def test_batched_unit_update_equals_the_per_model_update() -> None:
    (x0, p0), (x1, p1) = _random_state(6), _random_state(7)
    m = np.array([-3.0, 1.0, 120.0])
    sigma_m = np.diag([2.0, 2.0, 500.0]) * 1e-2
    xs, ps, loglik = _unit_update_all(np.stack([x0, x1]), np.stack([p0, p1]), m, sigma_m)
    for j, (x, p) in enumerate(((x0, p0), (x1, p1))):
        ref = _unit_update(x, p, m, sigma_m)
        np.testing.assert_allclose(xs[j], ref[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ps[j], ref[1], rtol=1e-8, atol=1e-12)
        assert loglik[j] == pytest.approx(ref[2], rel=1e-9)


def test_size_update_is_the_scalar_kalman_update_of_every_model() -> None:
    (x0, p0), (x1, p1) = _random_state(4), _random_state(5)
    h = np.zeros((1, TRACK_DIM))
    h[0, SIZE] = 1.0
    xs, ps = _size_update(np.stack([x0, x1]), np.stack([p0, p1]), 0.0365, 4e-8)
    for x, p, xn, pn in ((x0, p0, xs[0], ps[0]), (x1, p1, xs[1], ps[1])):
        ref = _generic_update(x, p, h, np.array([0.0365]), np.array([[4e-8]]))
        np.testing.assert_allclose(xn, ref[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(pn, ref[1], rtol=1e-8, atol=1e-14)


def test_unit_size_point_is_the_point_at_depth_one_over_s() -> None:
    meas = DirectionSize((400.0, 150.0), 12.0, -5.0, 0.006, 3e-4, 0.4, 0.02)
    m, cov = unit_size_point(meas, CAM)
    size = 0.036  # the target at z = R/s = 6 m
    expected = to_world(camera_point((400.0, 150.0), size / 0.006, (640, 480), 0.005, 31.0), 12, -5)
    np.testing.assert_allclose(size * m, expected, atol=1e-12)
    depth = DirectionDepth((400.0, 150.0), 12.0, -5.0, 1 / 0.006, 3e-4 / 0.006, 0.4, 0.02)
    np.testing.assert_allclose(cov, cartesian_measurement(depth, CAM)[1])


def test_size_feed_folds_the_pipelines_burst_size_in_once_with_its_sigma_scaled() -> None:
    feed = SizeFeed(Tracker3DConfig(burst_sigma_scale=2.0))
    _, none = feed.frame(FeedFrame(1.0, (320.0, 240.0), 0.0, 0.0, 0.006), CAM)
    assert none is None
    feed.burst(0.0362, 0.0001)  # replaced by the next burst before a tracking frame
    feed.burst(0.0358, 0.0002)
    _, size = feed.frame(FeedFrame(1.3, (320.0, 240.0), 0.0, 0.0, 0.0066), CAM)
    assert size == pytest.approx((0.0358, (2.0 * 0.0002) ** 2))  # R needs no transport
    _, again = feed.frame(FeedFrame(1.4, (320.0, 240.0), 0.0, 0.0, 0.0066), CAM)
    assert again is None  # a burst is used once
    feed.burst(0.0358, 0.0002)
    feed.reset()  # a new target
    assert feed.frame(FeedFrame(1.5, (320.0, 240.0), 0.0, 0.0, 0.0066), CAM)[1] is None


def test_size_track_waits_for_a_precise_size_to_start() -> None:
    tracker = Tracker3D.of_kind("mmae", Tracker3DConfig(start_size_sigma_rel=0.01))
    size, z = 0.036, 5.0
    unit = unit_size_point(DirectionSize((320.0, 240.0), 0.0, 0.0, size / z, 3e-4), CAM)
    # the start-up bursts measure R to ~9 %: no track on them (R̂ and p would drift to 0)
    assert tracker.step_size(0.0, unit, (size, (0.09 * size) ** 2)) is None
    assert tracker.step_size(0.1, unit) is None
    est = tracker.step_size(0.2, unit, (size, (0.002 * size) ** 2))
    assert est is not None
    assert est.position_m[2] == pytest.approx(z, rel=1e-6)


def test_size_track_starts_on_a_burst_learns_the_size_and_keeps_it_across_a_gap() -> None:
    rng = np.random.default_rng(21)
    tracker = Tracker3D.of_kind("mmae")
    size, cfg = 0.036, Tracker3DConfig()
    assert tracker.step_size(0.0, None) is None
    meas = lambda z: DirectionSize((320.0, 240.0), 0.0, 0.0, size / z, cfg.sigma_size_rel)  # noqa: E731
    assert tracker.step_size(0.0, unit_size_point(meas(5.0), CAM)) is None  # no size yet
    est = None
    for i in range(300):  # a static target at 5 m, a burst (1 % depth σ) every 10th frame
        t = i / 30
        burst = (size * (1 + rng.normal(0, 0.002)), (size * 0.002) ** 2) if i % 10 == 0 else None
        est = tracker.step_size(t, unit_size_point(meas(5.0), CAM), burst)
    assert est is not None
    assert est.position_m[2] == pytest.approx(5.0, abs=0.01)
    assert est.position_sigma_m[2] < 0.01
    # 3 s without anything, then a direction and size only: the track restarts with its size
    again = tracker.step_size(13.0, unit_size_point(meas(4.0), CAM))
    assert again is not None
    assert again.position_m[2] == pytest.approx(4.0, abs=0.01)
    assert again.velocity_m_s == (0.0, 0.0, 0.0)
    tracker.reset()  # a new target: no size known
    assert tracker.step_size(14.0, unit_size_point(meas(4.0), CAM)) is None


def test_direction_rate_is_the_derivative_of_the_centring_pan_tilt() -> None:
    p, v = np.array([1.2, -0.4, 5.0]), np.array([0.3, 0.05, -0.2])

    def pan_tilt(q: FloatArray) -> FloatArray:
        return np.degrees([math.atan2(q[0], q[2]), math.atan2(-q[1], math.hypot(q[0], q[2]))])

    # the direction that centres p: the world rotation at (pan, tilt) looks along p
    pan, tilt = pan_tilt(p)
    axis = world_rotation(float(pan), float(tilt)) @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(axis, p / np.linalg.norm(p), atol=1e-12)
    h = 1e-6
    expected = (pan_tilt(p + v * h) - pan_tilt(p - v * h)) / (2 * h)
    est = Track3DEstimate(0.0, tuple(p), tuple(v), (0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0))  # type: ignore[arg-type]
    np.testing.assert_allclose(direction_rate_deg_s(est), expected, rtol=1e-6)


def test_extrapolation_carries_the_last_estimate_without_a_step() -> None:
    tracker = Tracker3D.of_kind("mmae")
    assert tracker.extrapolate(0.0) is None
    for i in range(60):  # moving at 0.3 m/s along x at 5 m
        t = i / 30
        x = 0.3 * t
        u = CAM.principal_point_px[0] + x / 5.0 / (CAM.pixel_pitch_mm / CAM.image_distance_mm)
        meas = DirectionSize((u, CAM.principal_point_px[1]), 0.0, 0.0, 0.036 / 5.0, 3e-4)
        last = tracker.step_size(t, unit_size_point(meas, CAM), (0.036, 1e-9) if i == 0 else None)
    assert last is not None
    ahead = tracker.extrapolate(last.t + 0.1)
    assert ahead is not None
    v, a = np.array(last.velocity_m_s), np.array(last.acceleration_m_s2)
    np.testing.assert_allclose(
        ahead.position_m, np.array(last.position_m) + v * 0.1 + a * 0.005, atol=1e-12
    )
    assert ahead.position_sigma_m == last.position_sigma_m
    assert ahead.model_probabilities == last.model_probabilities
    assert tracker.estimate() == last  # the state did not move
    assert tracker.extrapolate(last.t + 5.0) is None  # beyond max_gap_s


def test_image_shift_is_the_head_turn_seen_on_a_world_fixed_point() -> None:
    """Positive pan turns right (a fixed point moves left), positive tilt up (it moves down);
    an off-centre point turned onto the axis lands on the principal point; no turn, no shift."""
    f_px = 31.0 / 0.0074
    size = (640, 480)
    centre = (319.5, 239.5)
    dx, dy = image_shift(centre, size, f_px, (0.0, 0.0), (1.0, 0.0))
    assert dx == pytest.approx(-f_px * math.tan(math.radians(1.0)), rel=1e-12)
    assert dy == 0.0
    dx, dy = image_shift(centre, size, f_px, (5.0, 0.0), (5.0, 1.0))
    assert dx == pytest.approx(0.0, abs=1e-9)
    assert dy == pytest.approx(f_px * math.tan(math.radians(1.0)), rel=1e-12)
    # a point seen off-centre: turning the head to its direction centres it
    pt = (500.0, 100.0)
    d = to_world(camera_point(pt, 1.0, size, 1.0, f_px), 3.0, -2.0)
    pan = math.degrees(math.atan2(d[0], d[2]))
    tilt = math.degrees(math.atan2(-d[1], math.hypot(d[0], d[2])))
    dx, dy = image_shift(pt, size, f_px, (3.0, -2.0), (pan, tilt))
    assert (pt[0] + dx, pt[1] + dy) == pytest.approx(centre, abs=1e-6)
    assert image_shift(pt, size, f_px, (3.0, -2.0), (3.0, -2.0)) == (0.0, 0.0)
