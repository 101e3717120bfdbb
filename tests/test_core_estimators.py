"""The estimator bank's start-up hand-over (dffd.core.estimators, docs/estimation.md §19)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from dffd.config import DffdConfig
from dffd.core.estimators import EstimatorBank
from dffd.core.outputs import Measurement
from dffd.core.synthetic import synthetic_lens
from dffd.wiring import pipeline_config

Z = 5.0  # m, a static target
SIZE = 0.01  # its normalised image size (constant: static)
FRAMES_PER_BURST = 7  # rolling bursts every 7th frame at 30 fps share an end frame
# 1/s: a size rate whose speed |ρ z| (0.05 m/s at 5 m) opens b's whole prior sigma_b0
MOVING_RATE = 0.01


def _seeded(
    bank: EstimatorBank, bursts: int, seed: int, rate: float = MOVING_RATE
) -> list[tuple[bool, float]]:
    """Feed a static target's bursts (Gaussian errors of 20 mm, stated 10 mm) to ``bank``,
    told the size rate ``rate`` (only b's prior reads it: the default opens the full
    ``sigma_b0``, as before docs/estimation.md §24); per burst: whether the LPV was seeded from
    the KF at it, and the KF's error cost (e_z² + e_b²/k2)/(2 k1) after it."""
    rng = np.random.default_rng(seed)
    lens = bank.lens
    g = bank.lpv_gains
    out: list[tuple[bool, float]] = []
    ends = rng.normal(0.0, 0.02 * math.sqrt(2.0), bursts + 1)
    for k in range(bursts):
        z_m = Z + 0.5 * (ends[k] + ends[k + 1])
        v = lens.v_from_depth(z_m)
        m = Measurement(
            burst_id=k + 1, t=k * FRAMES_PER_BURST / 30.0,
            frame_indices=(2 * k, 2 * k + 1, 2 * k + 2), focus_counts=(1, 2, 3),
            v_mm=(v - 0.05, v, v + 0.05), costs=(2.0, 1.0, 2.0), cost_sigmas=(0.01,) * 3,
            alpha=1.0, v_hat_mm=v, residual=0.0, accepted=True, reason="ok", z_m=z_m,
            sigma_m=0.01,
        )  # fmt: skip
        if k > 0:
            for _ in range(FRAMES_PER_BURST):
                bank.predict(1.0 / 30.0, SIZE, SIZE, 0.0, 0.0)
        bank.correct(m, SIZE, SIZE, rate)
        p = bank.unc.kf_covariance()
        cost = (p[0] + p[3] / g.k2) / (2.0 * g.k1_0)
        out.append((bank.lpv.z == bank.kf.z and bank.lpv.b == bank.kf.b, cost))
    return out


def test_start_up_seeding_ends_when_the_kf_has_converged() -> None:
    """By default the fixed-gain filters are seeded from the KF at every burst while the KF's
    error still costs the LPV less than at the previous burst, and never again after the first
    burst at which it does not (the KF has converged: further seeding would only hand its noise
    on). On this white static target that is after 30-110 bursts, not at a fixed count."""
    stops = []
    for seed in (1, 2, 3):
        bank = EstimatorBank(pipeline_config(DffdConfig()), synthetic_lens())
        rows = _seeded(bank, 160, seed)
        seeded = [s for s, _ in rows]
        stop = seeded.index(False)  # the first burst not seeded
        stops.append(stop)
        assert 20 < stop < 150, seed
        assert not any(seeded[stop:]), seed  # for good
        costs = [c for _, c in rows]
        # compared from the second burst on, where b's prior opens (docs/estimation.md §24)
        assert all(costs[k] < costs[k - 1] for k in range(2, stop)), seed
        assert costs[stop] >= costs[stop - 1], seed
    assert len(set(stops)) > 1  # the data decide


def test_start_up_seeding_by_count_when_configured() -> None:
    """``warmup_bursts`` = N restores the fixed count: seeded at exactly the first N bursts."""
    cfg = dataclasses.replace(pipeline_config(DffdConfig()), warmup_bursts=20)
    bank = EstimatorBank(cfg, synthetic_lens())
    seeded = [s for s, _ in _seeded(bank, 40, 1)]
    assert seeded == [True] * 20 + [False] * 20


def test_a_reset_starts_the_seeding_again() -> None:
    """A lost target restarts the filters: the next target is seeded from its own KF again."""
    bank = EstimatorBank(pipeline_config(DffdConfig()), synthetic_lens())
    first = [s for s, _ in _seeded(bank, 120, 4)]
    assert not first[-1]
    bank.reset()
    again = [s for s, _ in _seeded(bank, 3, 5)]
    assert again == [True, True, True]


def test_a_static_targets_kf_reads_no_velocity_into_its_noise() -> None:
    """b (the disturbance on ż = −ρz) gets the target's speed as its prior σ at the first
    update (DepthKF.open_b): told a size rate of 0, the KF does not read the first bursts'
    noise as a velocity (docs/estimation.md §24). With the fixed prior of 0.05 m/s
    (``MOVING_RATE`` here) b took several mm/s of burst noise in the first ten bursts."""
    for seed in (1, 2, 3):
        b_static, b_moving = [], []
        for rate, out in ((0.0, b_static), (MOVING_RATE, b_moving)):
            for n in range(2, 11):
                bank = EstimatorBank(pipeline_config(DffdConfig()), synthetic_lens())
                _seeded(bank, n, seed, rate)
                assert bank.kf.b is not None
                out.append(abs(bank.kf.b))
        assert max(b_static) < 0.001, seed
        assert max(b_moving) > 0.003, seed  # what the test would see without the speed prior
