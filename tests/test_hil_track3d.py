"""Bench scoring of the 3D trackers: the ``tracking_3d`` block and the model-probability plot."""

from __future__ import annotations

from pathlib import Path

import pytest

from dffd.core.tracking3d import Track3DEstimate
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
