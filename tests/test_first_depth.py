"""No depth is published before a burst with its vertex inside its bracket (issue 13).

Live on the default demo the first burst spans most of the focus range; its vertex lay outside
the bracket (extrapolated) at 15.2 m with σ 0.76 m while the target was at 10.0 m, and the first
estimates published that (a 6-7σ error). :class:`FirstDepthGate` holds the depths back until a
bracketed burst, or a bounded number of accepted bursts.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from dffd.core.pipeline import Estimate as CoreEstimate
from dffd.core.pipeline import Measurement as CoreMeasurement
from dffd.daemon.payloads import Payloads, without_depth
from dffd.first_depth import FIRST_DEPTH_FORCE_BURSTS, FIRST_DEPTH_MAX_BURSTS, FirstDepthGate
from dffd.recording import Truth
from dffd.replay import estimate_line, summarize

EXTRAPOLATED = CoreMeasurement(
    burst_id=1, t=1.0, frame_indices=(3, 4, 5), focus_counts=(7371, 16260, 22989),
    v_mm=(31.1, 31.3, 31.6), costs=(0.2, 0.5, 0.9), cost_sigmas=(0.01, 0.01, 0.01),
    alpha=1.0, v_hat_mm=31.06, residual=0.0, accepted=True,
    reason="vertex outside the bracket (extrapolated)", z_m=15.2, sigma_m=0.76,
)  # fmt: skip
BRACKETED = replace(EXTRAPOLATED, burst_id=2, reason="ok", z_m=9.99, sigma_m=0.04)
REJECTED = replace(EXTRAPOLATED, burst_id=3, accepted=False, reason="poor residual", z_m=None)
NO_DEPTH = {"measured": None, "cf1": None, "cf2": None, "lpv": None, "kf": None}
ESTIMATE = CoreEstimate(
    frame_index=7, t=12.5, state="tracking",
    depth_m={"measured": 15.2, "cf1": None, "cf2": 15.1, "lpv": 15.1, "kf": 15.1},
    measured_t=1.0, best="lpv", z_m=15.1, sigma_m=0.75, beta_m_s=0.0, lpv_b_m_s=0.0,
    size_m=0.054, r_px=22.0, rho=0.0, centroid_px=(330.0, 250.0),
    position_m=(0.1, 0.0, 15.1), velocity_m_s=(0.0, 0.0, 0.0),
    position_world_m=(0.1, 0.0, 15.1), velocity_world_m_s=(0.0, 0.0, 0.0),
    pan_deg=-1.0, tilt_deg=0.0, focus_counts=7371, inlier_fraction=1.0,
)  # fmt: skip
UNINITIALISED = replace(ESTIMATE, depth_m=NO_DEPTH, z_m=None, sigma_m=None)


def test_depths_wait_for_a_bracketed_burst() -> None:
    gate = FirstDepthGate()
    gate.on_measurement(EXTRAPOLATED)
    assert not gate.passes(ESTIMATE)  # initialised from an extrapolated vertex: held back
    gate.on_measurement(REJECTED)
    assert not gate.passes(ESTIMATE)
    gate.on_measurement(BRACKETED)
    assert gate.passes(ESTIMATE)
    assert gate.withheld == 2
    gate.on_measurement(EXTRAPOLATED)  # once open, later extrapolated bursts are published
    assert gate.passes(ESTIMATE)


def test_a_loss_closes_the_gate_again_and_it_cannot_stay_closed_for_ever() -> None:
    gate = FirstDepthGate()
    gate.on_measurement(BRACKETED)
    assert gate.passes(ESTIMATE)
    assert gate.passes(UNINITIALISED)  # filters reset (loss, release): nothing to hold back
    for _ in range(FIRST_DEPTH_MAX_BURSTS - 1):
        gate.on_measurement(EXTRAPOLATED)
        assert not gate.passes(ESTIMATE)
    gate.on_measurement(EXTRAPOLATED)  # a target outrunning its brackets is not hidden for ever
    assert gate.passes(ESTIMATE)


def test_a_first_depth_with_a_huge_sigma_waits_for_a_precise_one() -> None:
    """After a release and an automatic re-acquisition on the demo the first (full-range) burst
    bracketed its vertex at 10.5 m for a target at 8.1 m; the estimate said 11.6 m, σ 18 m."""
    gate = FirstDepthGate()
    wild = replace(BRACKETED, z_m=10.49, sigma_m=0.21)
    vague = replace(ESTIMATE, z_m=11.57, sigma_m=18.2)
    gate.on_measurement(wild)
    assert not gate.passes(vague)
    gate.on_measurement(replace(BRACKETED, z_m=7.73, sigma_m=0.009))
    assert gate.passes(replace(ESTIMATE, z_m=7.62, sigma_m=0.2))
    # The filters' start-up σ of a good first burst passes at once (static world: 26 %).
    gate = FirstDepthGate()
    gate.on_measurement(replace(BRACKETED, z_m=3.974, sigma_m=0.004))
    assert gate.passes(replace(ESTIMATE, z_m=3.972, sigma_m=1.047))
    # A σ that never shrinks does not hide the depths for ever either.
    gate = FirstDepthGate()
    for _ in range(FIRST_DEPTH_FORCE_BURSTS - 1):
        gate.on_measurement(wild)
        assert not gate.passes(vague)
    gate.on_measurement(wild)
    assert gate.passes(vague)


def test_a_held_back_estimate_keeps_its_image_fields_and_loses_every_depth() -> None:
    payload = Payloads("lpv").estimate(ESTIMATE)
    assert payload is not None
    held = without_depth(payload)
    assert held.model_dump()["depth_m"] == NO_DEPTH
    for key in ("z_m", "sigma_m", "size_m", "position_m", "velocity_m_s"):
        assert getattr(held, key) is None
    assert (held.r_px, held.pan_deg, held.seq) == (payload.r_px, payload.pan_deg, payload.seq)


def test_replay_scores_from_the_first_published_estimate_and_counts_the_held_back_ones() -> None:
    """The gate is the core step's (dffd.step): replay's lines of held-back estimates carry null
    filter depths, as the daemon's payloads do, and its summary scores the filters from the
    first published estimate on; the burst's own depth is scored either way."""
    held = estimate_line(ESTIMATE, published=False)
    assert held["published"] is False
    assert held["depth_m"] == {**NO_DEPTH, "measured": 15.2}
    assert all(v is None for v in held["sigma_m"].values())
    for key in ("z_m", "size_m", "position_m"):
        assert held[key] is None
    depth = {"measured": 10.01, "cf1": None, "cf2": 10.02, "lpv": 10.02, "kf": 10.03}
    sigma = {"lpv": 0.05, "kf": 0.05, "cf2": 0.05, "measured": 0.04}
    good = replace(
        ESTIMATE, t=13.0, frame_index=8, z_m=10.02, sigma_m=0.05, depth_m=depth, sigma_by=sigma
    )
    lines = [held, estimate_line(good, published=True)]
    truth = Truth(t_s=np.array([0.0, 20.0]), z_m=np.array([10.0, 10.0]))
    summary = summarize(lines, truth, 0.0, 0.0, bursts=(2, 0))
    assert summary["withheld_estimates"] == 1
    lpv = summary["estimators"]["lpv"]
    assert lpv["n"] == 1  # the 15.1 m held back is not scored: only the published 10.02 m
    assert abs(lpv["first_abs_err_m"] - 0.02) < 1e-9
    assert summary["estimators"]["measured"]["n"] == 2
