"""dffd calibrate against the simulated camera: focus table vs the simulator's ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from dffd.calibrate import (
    DEFAULT_SIM_CAMERA_FILE,
    CalibrationError,
    DepthPoint,
    SimRig,
    configure_parser,
    lens_from_points,
    run,
    vertex,
)
from dffd.core.lens import Lens

TRUTH = Lens.from_toml(Path(__file__).resolve().parent.parent / "config/lenses/sim-evi-d100.toml")
# Measured bias of the sweep on the reference simulator: the sharpest counts come out 15–80
# counts on the far side of the true table (≤ 2% in depth at 10 m). 120 counts bounds it.
COUNTS_TOL = 120


def test_vertex_of_a_parabola() -> None:
    import numpy as np

    x = np.arange(0.0, 20.0)
    assert vertex(x, (x - 7.3) ** 2 + 1.0) == pytest.approx(7.3, abs=1e-6)


def test_non_monotone_points_are_refused() -> None:
    points = [
        DepthPoint(2.0, 100, 31.5, 1.0),
        DepthPoint(4.0, 200, 31.4, 1.0),
        DepthPoint(3.0, 300, 31.6, 1.0),
    ]
    with pytest.raises(CalibrationError, match="monotone"):
        lens_from_points("x", 31.0, 0.005, points)


def test_sim_sweep_matches_the_ground_truth_and_latency() -> None:
    rig = SimRig(DEFAULT_SIM_CAMERA_FILE)
    for z in (1.5, 4.0, 10.0):
        point = rig.sharpest(z)
        assert abs(point.counts - TRUTH.counts_for_depth(z)) <= COUNTS_TOL, (z, point)
        assert point.v_mm == pytest.approx(TRUTH.v_from_depth(z))
    assert rig.latency_frames() == round(rig.config.capture.capture_latency_frames)


def test_cli_writes_a_loadable_lens_file(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    out = tmp_path / "lens.toml"
    args = parser.parse_args(["--sim", "--depths", "2,5,12", "--out", str(out)])
    assert run(args) == 0
    lens = Lens.from_toml(out)
    assert len(lens.focus_counts) == 3
    assert lens.depth_from_v(lens.v_from_counts(TRUTH.counts_for_depth(5.0))) == pytest.approx(
        5.0, rel=0.03
    )
    assert run(parser.parse_args(["--depths", "2,5"])) == 2  # hardware mode: not implemented
