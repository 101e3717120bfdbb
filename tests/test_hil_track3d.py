"""Bench scoring of the 3D trackers: the ``tracking_3d`` block and the model-probability plot."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from dffd.core.tracking3d_types import Track3DEstimate
from hil.track3d import Track3DScore, Truth3D, pooled_block


def estimate(t: float, dx: float, dw: float, probs: dict[str, float]) -> Track3DEstimate:
    return Track3DEstimate(
        t=t,
        position_m=(1.0 + dx, 0.0, 5.0),
        velocity_m_s=(0.2, 0.0, 0.0 + dx),
        acceleration_m_s2=(0.0, 0.0, 0.01),
        angular_speed_rad_s=0.05 + dw,
        position_sigma_m=(0.01, 0.01, 0.03),
        model_probabilities=probs,
    )


TRUTH = Truth3D((1.0, 0.0, 5.0), (0.2, 0.0, 0.0), (0.0, 0.0, 0.01), 0.05)


def test_block_is_steady_state_rms_and_bias_per_filter(tmp_path: Path) -> None:
    score = Track3DScore(settle_s=2.0)
    for i in range(10):
        t = float(i)
        # before settling: huge errors that must not count
        dx = 100.0 if t < 2.0 else (0.03 if i % 2 else -0.03)
        score.add(
            t,
            TRUTH,
            {
                "mmae": estimate(t, dx, 0.004, {"cv": 0.2, "ca": 0.1, "ct": 0.7}),
                "cv": estimate(t, 2 * dx, -0.05, {"cv": 1.0}),
            },
        )
    block = score.block()
    assert set(block) == {"mmae", "cv"}
    mm = block["mmae"]
    assert mm["n"] == 8
    assert mm["position_rms_m"] == pytest.approx(0.03)
    # the x error split along the line of sight to (1, 0, 5) and across it
    assert mm["position_los_rms_m"] == pytest.approx(0.03 / math.sqrt(26))
    assert mm["position_lateral_rms_m"] == pytest.approx(0.03 * 5 / math.sqrt(26))
    assert mm["velocity_rms_m_s"] == pytest.approx(0.03)
    assert mm["acceleration_rms_m_s2"] == pytest.approx(0.0)
    assert mm["angular_speed"] == {
        "bias_rad_s": pytest.approx(0.004),
        "rms_rad_s": pytest.approx(0.004),
        "truth_mean_rad_s": pytest.approx(TRUTH.angular_speed_rad_s),
    }
    assert block["cv"]["position_rms_m"] == pytest.approx(0.06)
    assert block["cv"]["angular_speed"]["bias_rad_s"] == pytest.approx(-0.05)
    png = score.plot(tmp_path / "probs.png", "test")
    assert png is not None
    assert png.stat().st_size > 1000
    pooled = pooled_block([score, score])
    assert pooled["mmae"]["n"] == 16
    assert pooled["mmae"]["position_rms_m"] == pytest.approx(0.03)


def test_no_frames_after_settling_gives_none() -> None:
    score = Track3DScore(settle_s=100.0)
    score.add(1.0, TRUTH, {"cv": estimate(1.0, 0.0, 0.0, {"cv": 1.0})})
    assert score.block() == {"cv": None}


def test_realtime_scores_the_published_track_against_the_truth_topic() -> None:
    from types import SimpleNamespace

    from dffd.daemon.payloads import truth_payload
    from hil.realtime import _score_3d, _truth_3d

    # The daemon's truth payload carries the 3D truth; the bench reads it back.
    frame_truth = SimpleNamespace(
        z_m=5.0,
        position_world_m=TRUTH.position_m,
        size_m=0.036,
        velocity_world_mps=TRUTH.velocity_m_s,
        acceleration_world_mps2=TRUTH.acceleration_m_s2,
        angular_speed_rad_s=TRUTH.angular_speed_rad_s,
    )
    payload = truth_payload(1.0, frame_truth).model_dump(mode="json")
    assert _truth_3d(payload) == TRUTH
    assert _truth_3d({**payload, "angular_speed_rad_s": None}) is None  # an older simulator
    truth = {round(100.0 + i, 4): TRUTH for i in range(10)}
    estimates = []
    for i in range(10):
        e = estimate(100.0 + i, 0.03 if i % 2 else -0.03, 0.004, {"cv": 0.5, "ca": 0.5})
        estimates.append(
            {
                "t_mono": e.t,
                "position_m": list(e.position_m),
                "velocity_m_s": list(e.velocity_m_s),
                "acceleration_m_s2": list(e.acceleration_m_s2),
                "angular_speed_rad_s": e.angular_speed_rad_s,
                "position_sigma_m": list(e.position_sigma_m),
                "model_probabilities": e.model_probabilities,
            }
        )
    estimates.append({"t_mono": 111.0, "position_m": [0.0, 0.0, 1.0], "position_sigma_m": None})
    score = _score_3d(estimates, truth, settle_s=2.0, t0=100.0)
    assert score is not None
    block = score.block()
    assert block["mmae"]["n"] == 8  # t − t0 ≥ 2 s; the estimate without a track is skipped
    assert block["mmae"]["position_rms_m"] == pytest.approx(0.03)
    assert block["mmae"]["angular_speed"]["bias_rad_s"] == pytest.approx(0.004)
    assert _score_3d(estimates, {}, settle_s=2.0, t0=100.0) is None
