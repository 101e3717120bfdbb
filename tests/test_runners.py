"""One core for every runner: the daemon's estimator path, the lock-step bench and ``dffd replay``
give the same estimates and the same scheduler feedback on one recorded frame sequence."""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path
from typing import Any

import pytest

from dffd.cli import main as dffd_main
from dffd.config import DffdConfig
from dffd.core.lens import Lens
from dffd.core.types import FrameTag
from dffd.daemon.estimator import EstimatorResult, EstimatorThread
from dffd.recording import RecordingWriter
from dffd.replay import estimate_line
from dffd.step import StepResult
from dffd.wiring import build_core
from drivers.frames import Frame
from drivers.sim.source import FrameTruth
from hil.lockstep import run_session
from hil.runner import RecordingSink
from hil.scenario import load_scenario
from hil.simbuild import build_session

# The estimator thread processes a 6 s run in well under this; it only bounds a broken test.
ESTIMATOR_DONE_TIMEOUT_S = 60.0
REPLAY_TOLERANCE_M = 1e-9  # issue 10: replay reproduces the bench's estimates to 1e-9

# A target moving toward the camera: acquisition on the start-up transit frames, bursts, and
# transit frames while tracking; short enough for a unit test.
SCENARIO = """
name = "runners"
description = "test: disc approaching from 3 m"
duration_s = 6.0
settle_s = 3.0
seeds = [11]

[target]
shape = "disc"
size_m = 0.03576
known_size_m = 0.03576

[trajectory]
kind = "linear"
position_m = [0.0, 0.0, 3.0]
end_m = [0.0, 0.0, 2.0]
speed_mps = 0.3
"""


class _Recorded:
    """The bench's frames (a FrameSink, also written to disk) and its core steps."""

    def __init__(self, sink: RecordingSink) -> None:
        self.sink = sink
        self.frames: list[tuple[Frame, FrameTag]] = []
        self.steps: list[StepResult] = []

    def add(self, frame: Frame, tag: FrameTag, truth: FrameTruth) -> None:
        self.frames.append((frame, tag))
        self.sink.add(frame, tag, truth)


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[_Recorded, Path, DffdConfig]:
    base = tmp_path_factory.mktemp("runners")
    path = base / "runners.toml"
    path.write_text(SCENARIO, "utf-8")
    scenario = load_scenario(path)
    case, traj = scenario.expand()[0]
    seed = scenario.seeds[0]
    session = build_session(scenario, traj, seed)
    lens = Lens.from_toml(session.lens_path)
    rec_dir = base / "recording"
    with RecordingWriter(rec_dir, session.fps, session.frame_size, lens.to_meta()) as writer:
        recorded = _Recorded(RecordingSink(writer))
        run_session(
            scenario, case, traj, seed, recorder=recorded, on_step=recorded.steps.append
        )  # fmt: skip
    # The service configuration the bench runs with: defaults, the scenario's lens and size.
    settings = DffdConfig.model_validate(
        {
            "lens": {"file": str(session.lens_path)},
            "target": {"known_size_m": scenario.target.known_size_m},
        }
    )
    return recorded, rec_dir, settings


def test_the_daemon_estimator_path_matches_the_bench(
    bench: tuple[_Recorded, Path, DffdConfig],
) -> None:
    recorded, _, settings = bench
    assert len(recorded.steps) == len(recorded.frames) > 100
    results: list[EstimatorResult] = []
    done = threading.Event()

    def deliver(result: EstimatorResult) -> None:
        results.append(result)
        if len(results) == len(recorded.frames):
            done.set()

    core = build_core(settings, Lens.from_toml(settings.lens.file))
    est = EstimatorThread(core, deliver, queue_max=len(recorded.frames))
    est.start()
    try:
        for frame, tag in recorded.frames:
            est.submit(frame, tag)
        assert done.wait(ESTIMATOR_DONE_TIMEOUT_S)
    finally:
        assert est.stop()
    assert est.dropped == 0
    tracked = 0
    for daemon, bench_step in zip(results, recorded.steps, strict=True):
        step = daemon.step
        assert step.frame_index == bench_step.frame_index
        assert step.feedback == bench_step.feedback
        assert step.output.state == bench_step.output.state
        assert step.output.measurement == bench_step.output.measurement
        # The daemon runs the published 3D tracker only; the bench runs every kind on the same
        # frames, and the published one agrees.
        assert step.track == bench_step.track
        assert set(step.tracks) <= {"mmae"}
        d_est, b_est = step.output.estimate, bench_step.output.estimate
        assert (d_est is None) == (b_est is None)
        if d_est is not None and b_est is not None:
            # the same first-depth gate in both (dffd.first_depth): the same depths held back
            assert step.published == bench_step.published
            d_line = estimate_line(d_est, step.track, published=step.published)
            assert d_line == estimate_line(b_est, bench_step.track, published=bench_step.published)
            tracked += 1
    # The comparison covered tracking, bursts and transit frames (not an empty run).
    assert tracked >= 20
    roles = {tag.role for _, tag in recorded.frames}
    assert roles == {"track", "burst", "transit"}
    assert any(s.output.measurement is not None for s in recorded.steps)
    assert any(set(s.tracks) == {"mmae", "imm", "cv"} for s in recorded.steps)


def test_replay_with_the_service_config_reproduces_the_bench(
    bench: tuple[_Recorded, Path, DffdConfig], tmp_path: Path
) -> None:
    recorded, rec_dir, settings = bench
    config = tmp_path / "dffd.toml"
    config.write_text(settings.to_toml(), "utf-8")
    out = tmp_path / "est.jsonl"
    assert dffd_main(["replay", str(rec_dir), "--out", str(out), "--config", str(config)]) == 0
    replayed = [json.loads(line) for line in out.read_text("utf-8").splitlines()]
    expected = [
        json.loads(json.dumps(estimate_line(s.output.estimate, s.track, published=s.published)))
        for s in recorded.steps
        if s.output.estimate is not None
    ]
    assert len(replayed) == len(expected) >= 20
    for got, want in zip(replayed, expected, strict=True):
        # the offline smoother is replay's own (it needs the whole recording); every causal
        # estimator must be the bench's, bit for bit
        assert got["depth_m"].pop("smoothed") is not None or got["depth_m"]["kf"] is None
        got["sigma_m"].pop("smoothed")
        _assert_close(got, want, f"frame {want['frame']}")


def _assert_close(got: Any, want: Any, where: str) -> None:
    if isinstance(want, dict):
        assert set(got) == set(want), where
        for key in want:
            _assert_close(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, list):
        assert len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            _assert_close(g, w, f"{where}[{i}]")
    elif isinstance(want, float) and not isinstance(want, bool):
        assert isinstance(got, float), where
        assert math.isclose(got, want, rel_tol=0.0, abs_tol=REPLAY_TOLERANCE_M), where
    else:
        assert got == want, where
