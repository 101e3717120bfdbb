"""The 3D trackers' numerics pinned on a recorded run: speed work must not move an estimate.

``data/track3d_trace.npz`` holds every call the service's core made to its tracker bank in two
lock-step runs of the reference simulator (``paper-circle`` and ``figure-eight``, 700 timed
frames each, the bench's core: ``hil.bench_core``): ``step_size`` with the unit-size point, its
covariance and the burst size, ``extrapolate`` and ``reset``. The expected outputs of every
tracker kind were computed from those inputs by the tracker before its speed-up (commit d43666c;
main's tracker at 7fd3d2b, with its start rule, gives the same outputs) with the configuration
spelled out below, so a change of the defaults does not touch this test.

A change of the trackers' *semantics* (models, updates, combination) changes the outputs on
purpose: regenerate them from the stored inputs with the tracker of the tree you are in,
``PYTHONPATH=. python tests/test_core_tracking3d_trace.py --regenerate`` (from the repository
root; without it an installed ``dffd`` may be imported instead), and say so in the commit.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from dffd.core import kernel_dispatch, kernels, kernels_numpy
from dffd.core.tracking3d import Tracker3DBank
from dffd.core.tracking3d_types import (
    TRACKER_KINDS,
    Track3DEstimate,
    Tracker3DConfig,
    TrackerKind,
)

TRACE = Path(__file__).parent / "data" / "track3d_trace.npz"
# Rows of ``calls``: op (0 step_size, 1 extrapolate, 2 reset), t, m (3), Σ_m (9), (R, σ_R²);
# NaN where absent. Rows of the outputs: position, velocity, acceleration (3 each), angular
# speed, position σ (3), probabilities of cv, ca, ct; NaN where no track.
OUT_WIDTH = 16
MODEL_NAMES = ("cv", "ca", "ct")
# The configuration the outputs were computed with (the defaults at commit 7fd3d2b).
CONFIG = Tracker3DConfig(
    q_cv_m2_s3=1e-4,
    q_cv_single_m2_s3=1e-2,
    q_ca_m2_s5=2e-2,
    q_ct_m2_s3=1e-4,
    q_omega_rad2_s3=1e-5,
    probability_floor=1e-3,
    switch_rate_hz=0.2,
    init_sigma_v_m_s=1.0,
    init_sigma_a_m_s2=0.5,
    init_sigma_omega_rad_s=0.3,
    max_gap_s=1.0,
    q_size_m2_s=1e-12,
    start_size_sigma_rel=0.01,
    sigma_size_rel=3e-4,
    sigma_px=0.3,
    sigma_angle_deg=0.03,
    burst_sigma_scale=2.0,
)
# Reordered floating-point sums (stacked products, cofactor inverses) move the last bits only.
RTOL = 1e-9
ATOL = 1e-9  # m, m/s, m/s², rad/s and probabilities alike


@pytest.mark.parametrize("impl", ["compiled", "numpy"])
@pytest.mark.parametrize("kind", TRACKER_KINDS)
def test_tracker_outputs_match_the_recorded_run(kind: TrackerKind, impl: str) -> None:
    """Both kernel implementations (dffd.core.kernels_track and its NumPy twins) give the
    recorded outputs."""
    data = np.load(TRACE)
    calls, expected = data["calls"], data[f"outs_{kind}"]
    with kernel_dispatch.using(kernels if impl == "compiled" else kernels_numpy):
        got = replay(calls, kind)
    assert np.array_equal(np.isnan(got), np.isnan(expected)), "a track appeared or vanished"
    np.testing.assert_allclose(got, expected, rtol=RTOL, atol=ATOL, equal_nan=True)
    # The run exercised what it pins: size and direction updates, bursts, gaps, extrapolation.
    assert (calls[:, 0] == 0).sum() > 200
    assert (calls[:, 0] == 1).sum() > 1000
    assert np.isfinite(calls[:, 14]).sum() > 50
    if kind != "cv":
        assert np.nanmax(np.abs(expected[:, 9])) > 0.05  # figure-eight: the turn model turns


def replay(calls: npt.NDArray[np.float64], kind: TrackerKind) -> npt.NDArray[np.float64]:
    """Every recorded call on a fresh bank of ``kind``; one output row per call."""
    bank = Tracker3DBank((kind,), CONFIG)
    rows = []
    for row in calls:
        op, t = int(row[0]), float(row[1])
        if op == 2:
            bank.reset()
            rows.append(_row(None))
            continue
        if op == 1:
            out = bank.extrapolate(t)
        else:
            unit = None if np.isnan(row[2]) else (row[2:5].copy(), row[5:14].reshape(3, 3).copy())
            size = None if np.isnan(row[14]) else (float(row[14]), float(row[15]))
            out = bank.step_size(t, unit, size)
        rows.append(_row(out.get(kind)))
    return np.array(rows)


def _row(est: Track3DEstimate | None) -> list[float]:
    if est is None:
        return [np.nan] * OUT_WIDTH
    probs = [est.model_probabilities.get(name, np.nan) for name in MODEL_NAMES]
    return [
        *est.position_m,
        *est.velocity_m_s,
        *est.acceleration_m_s2,
        est.angular_speed_rad_s,
        *est.position_sigma_m,
        *probs,
    ]


def _regenerate() -> None:
    """Recompute every kind's outputs from the stored inputs with the current tracker."""
    calls = np.load(TRACE)["calls"]
    outs = {f"outs_{kind}": replay(calls, kind) for kind in TRACKER_KINDS}
    np.savez_compressed(TRACE, calls=calls, **outs)  # type: ignore[arg-type]
    print(f"{TRACE}: {len(calls)} calls, outputs of {', '.join(TRACKER_KINDS)} rewritten")


if __name__ == "__main__":
    if sys.argv[1:] != ["--regenerate"]:
        sys.exit("usage: python tests/test_core_tracking3d_trace.py --regenerate")
    _regenerate()
