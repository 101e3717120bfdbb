"""Daemon shell pieces that need no camera: estimator thread queue, rate meter, console view."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console as RichConsole

from dffd.core.pipeline import PipelineOutput
from dffd.core.types import FrameTag
from dffd.daemon.console import ConsoleSnapshot, render
from dffd.daemon.estimator import EstimatorResult, EstimatorThread
from dffd.daemon.status import RateMeter
from dffd.step import CoreStep
from drivers.frames import Frame
from tests.conftest import free_port

# The estimator thread hands results over within milliseconds; 5 s only bounds a broken test.
RESULT_TIMEOUT_S = 5.0


class _BlockingPipeline:
    """Stands in for the core: blocks on the first frame until released."""

    state = "acquiring"

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        self.seen: list[int] = []
        self.known_size: float | None = None

    def process(self, frame: Frame, tag: FrameTag) -> PipelineOutput:
        self.entered.set()
        self.release.wait(RESULT_TIMEOUT_S)
        self.seen.append(frame.index)
        return PipelineOutput("acquiring", None, None, None)

    def predicted_depth(self) -> None:
        return None

    def set_known_size(self, size: float | None) -> None:
        self.known_size = size


def _frame(i: int) -> Frame:
    return Frame(i, i / 30.0, np.zeros((4, 4), dtype=np.uint8))


def test_estimator_queue_drops_oldest_and_never_blocks_capture() -> None:
    pipeline = _BlockingPipeline()
    results: list[EstimatorResult] = []
    done = threading.Event()

    def deliver(result: EstimatorResult) -> None:
        results.append(result)
        if result.frame_index == 9:
            done.set()

    est = EstimatorThread(CoreStep(pipeline), deliver, queue_max=3)  # type: ignore[arg-type]
    est.start()
    tag = FrameTag("track", 5000, 0.0, 0.0)
    est.submit(_frame(0), tag)
    assert pipeline.entered.wait(RESULT_TIMEOUT_S)
    # Frame 0 is being processed (blocked); 1…9 arrive: only the newest 3 stay queued.
    for i in range(1, 10):
        est.submit(_frame(i), tag)
    future = est.call(lambda p: p.set_known_size(0.03) or {"ok": True})  # type: ignore[attr-defined]
    pipeline.release.set()
    assert done.wait(RESULT_TIMEOUT_S)
    assert future.result(RESULT_TIMEOUT_S) == {"ok": True}
    assert pipeline.known_size == 0.03
    assert est.stop()
    assert pipeline.seen == [0, 7, 8, 9]
    assert est.dropped == 6


class _FailingPipeline(_BlockingPipeline):
    """The core raising on frame 1 (a bad frame) and on a bad command."""

    def process(self, frame: Frame, tag: FrameTag) -> PipelineOutput:
        if frame.index == 1:
            raise ValueError("garbled frame")
        self.seen.append(frame.index)
        return PipelineOutput("acquiring", None, None, None)

    def set_known_size(self, size: float | None) -> None:
        raise ValueError(f"size {size} rejected")


def test_a_frame_or_command_that_raises_does_not_stop_the_estimator() -> None:
    pipeline = _FailingPipeline()
    delivered: list[int] = []
    done = threading.Event()

    def deliver(result: EstimatorResult) -> None:
        delivered.append(result.frame_index)
        if result.frame_index == 2:
            done.set()

    est = EstimatorThread(CoreStep(pipeline), deliver)  # type: ignore[arg-type]
    est.start()
    tag = FrameTag("track", 5000, 0.0, 0.0)
    future = est.call(lambda p: p.set_known_size(-1.0) or None)  # type: ignore[attr-defined]
    for i in range(3):
        est.submit(_frame(i), tag)
    assert done.wait(RESULT_TIMEOUT_S)
    assert isinstance(future.exception(RESULT_TIMEOUT_S), ValueError)
    assert est.stop()
    assert delivered == [0, 2]
    assert pipeline.seen == [0, 2]


def test_rate_meter() -> None:
    meter = RateMeter(window_s=2.0)
    for k in range(61):
        meter.add(k / 30.0)
    assert abs(meter.rate(2.0) - 30.0) < 1.0
    assert meter.rate(100.0) == 0.0


def test_console_renders_a_snapshot() -> None:
    snap = ConsoleSnapshot(
        camera="sim", state="tracking", uptime_s=12.0, frame_hz=30.0, estimate_hz=7.0,
        depth_hz=0.9, depth_limit_hz=1.0, link_connected=True, link_timeouts=0, link_errors=0,
        link_reconnects=0, mqtt_connected=False, mqtt_backlog=3, frames_dropped=1,
        bursts_accepted=5, bursts_rejected=1, roles={"track": 10, "burst": 3, "transit": 7},
        depth_m={"measured": None, "lpv": 4.01, "kf": 3.99}, best="lpv", truth_z_m=4.0,
    )  # fmt: skip
    console = RichConsole(record=True, width=120)
    console.print(render(snap))
    text: Any = console.export_text()
    assert "tracking" in text
    assert "lpv (best)" in text
    assert "0.010" in text  # lpv error against the truth
    assert "DOWN" in text  # MQTT down is shown


def test_sim_world_comes_from_the_scenario_file(tmp_path: Any) -> None:
    """The daemon's world is the scenario TOML read through the simulator's own config types."""
    from pathlib import Path

    from dffd.config import load_config
    from dffd.wiring import sim_camera_config

    sim = sim_camera_config(load_config(None))
    traj = sim.world.trajectory
    assert (traj.kind, traj.center_m, traj.radius_m, traj.speed_mps) == (
        "circle", (0.0, 0.0, 6.0), 4.0, 0.25,
    )  # fmt: skip
    assert traj.phase_deg == 180.0  # sim.start_phase_deg overrides the scenario's 0°
    assert sim.world.target.size_m == 0.03576
    scenario = Path(tmp_path) / "spin.toml"
    scenario.write_text(
        '[target]\nshape = "polygon"\nsides = 5\nrotation_dps = 20.0\n'
        '[trajectory]\nkind = "static"\nposition_m = [0.0, 0.0, 3.0]\n',
        encoding="utf-8",
    )
    cfg = load_config(None).model_copy(deep=True)
    cfg.sim.scenario = str(scenario)
    sim = sim_camera_config(cfg)
    assert sim.world.target.shape == "polygon"
    assert sim.world.target.rotation_dps == 20.0
    assert sim.world.trajectory.position_m == (0.0, 0.0, 3.0)


def test_a_core_output_that_does_not_fit_the_schema_is_skipped_not_fatal() -> None:
    from dffd.daemon.payloads import Payloads
    from dffd.mqtt import models

    payloads = Payloads("lpv")

    def cut_short(_: object) -> models.Measurement:  # a burst cut by a link fault: 2 frames
        return models.Measurement(
            seq=1, burst=1, t=0.0, t_mono=0.0, focus_counts=[1, 2], costs=[1.0, 2.0],
            fit=models.Fit(accepted=False, reason="too few samples"),
        )  # fmt: skip

    assert payloads.or_none(cut_short, None) is None
    assert payloads.or_none(cut_short, None) is None
    assert payloads.skipped == 2


def test_the_estimate_payload_carries_the_3d_track_and_fits_the_shipped_schema() -> None:
    import json
    from pathlib import Path

    import jsonschema

    from dffd.core.pipeline import Estimate as CoreEstimate
    from dffd.core.tracking3d_types import Track3DEstimate
    from dffd.daemon.payloads import Payloads

    est = CoreEstimate(
        frame_index=7, t=12.5, state="tracking",
        depth_m={"measured": None, "cf1": None, "cf2": 2.0, "lpv": 2.01, "kf": 2.0},
        measured_t=None, best="lpv", z_m=2.01, sigma_m=0.02, beta_m_s=0.0, lpv_b_m_s=0.0,
        size_m=0.036, r_px=40.0, rho=0.0, centroid_px=(330.0, 250.0),
        position_m=(0.01, 0.02, 2.01), velocity_m_s=(0.0, 0.0, 0.1),
        position_world_m=(0.01, 0.02, 2.01), velocity_world_m_s=(0.0, 0.0, 0.1),
        pan_deg=0.0, tilt_deg=0.0, focus_counts=0x4000, inlier_fraction=1.0,
    )  # fmt: skip
    track = Track3DEstimate(
        t=12.5, position_m=(0.011, 0.019, 2.0), velocity_m_s=(0.2, 0.0, 0.05),
        acceleration_m_s2=(0.0, 0.0, -0.04), angular_speed_rad_s=0.2,
        position_sigma_m=(0.001, 0.001, 0.02),
        model_probabilities={"cv": 0.1, "ca": 0.2, "ct": 0.7},
    )  # fmt: skip
    schema_file = Path(__file__).resolve().parent.parent / "dffd/schemas/estimate.schema.json"
    validator = jsonschema.Draft202012Validator(json.loads(schema_file.read_text("utf-8")))
    payloads = Payloads("lpv")
    with_track = payloads.estimate(est, track)
    assert with_track is not None
    doc = json.loads(with_track.to_json())
    validator.validate(doc)
    assert doc["position_m"] == list(track.position_m)  # the tracker's, not the raw point
    assert doc["velocity_m_s"] == list(track.velocity_m_s)
    assert doc["acceleration_m_s2"] == list(track.acceleration_m_s2)
    assert doc["angular_speed_rad_s"] == 0.2
    assert doc["position_sigma_m"] == list(track.position_sigma_m)
    assert doc["model_probabilities"] == {"cv": 0.1, "ca": 0.2, "ct": 0.7}
    without = payloads.estimate(est)
    assert without is not None
    doc = json.loads(without.to_json())
    validator.validate(doc)  # every key present, the tracker's null
    assert doc["position_m"] == list(est.position_world_m)
    for key in ("acceleration_m_s2", "angular_speed_rad_s", "position_sigma_m"):
        assert doc[key] is None
    assert doc["model_probabilities"] is None
    bad = dict(doc, model_probabilities={"cv": 1.5})
    with pytest.raises(jsonschema.ValidationError):
        validator.validate(bad)


async def test_a_core_command_the_busy_estimator_cannot_apply_is_rejected_with_advice(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from dffd.daemon import commands
    from dffd.mqtt.commands import CommandRejected

    monkeypatch.setattr(commands, "CORE_COMMAND_TIMEOUT_S", 0.05)  # shrunk, not slept on
    pipeline = _BlockingPipeline()
    est = EstimatorThread(CoreStep(pipeline), lambda _r: None)  # type: ignore[arg-type]
    est.start()
    try:
        est.submit(_frame(0), FrameTag("track", 5000, 0.0, 0.0))
        assert pipeline.entered.wait(RESULT_TIMEOUT_S)  # the core is busy on frame 0
        with pytest.raises(CommandRejected, match=r"did not apply the command.*retry"):
            await commands.apply_to_core(est, lambda p: p.release())
    finally:
        pipeline.release.set()
        assert est.stop()


class _OverdueScheduler:
    """A scheduler whose wake-up time is always in the past and which never acts."""

    def __init__(self) -> None:
        self.calls = 0

    def next_actions(self, now: float) -> list[object]:
        self.calls += 1
        return []

    def next_wakeup(self) -> float:
        return 0.0


async def test_scheduler_loop_yields_to_the_event_loop_when_a_wakeup_is_overdue() -> None:
    import asyncio

    from dffd.config import load_config
    from dffd.daemon.app import SCHEDULER_MIN_WAIT_S, Daemon

    daemon = Daemon(load_config(None))
    sched = _OverdueScheduler()
    daemon.scheduler = sched  # type: ignore[assignment]
    dispatched: list[object] = []
    task = asyncio.create_task(daemon._scheduler_loop(dispatched.append))
    try:
        for _ in range(3):  # would never return here if the loop did not yield
            await asyncio.sleep(0)
        # The overdue scheduler is polled again, but not in a busy loop: between polls the
        # shell waits at least SCHEDULER_MIN_WAIT_S.
        window_s = 50 * SCHEDULER_MIN_WAIT_S
        started = sched.calls
        await asyncio.sleep(window_s)  # a measurement window, not a wait for an event
        assert sched.calls - started >= 2
        assert sched.calls - started <= 51
        assert not task.done()  # still running, not ended by an exception
        assert dispatched == []
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_a_camera_port_the_link_cannot_parse_is_a_clean_failure(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The config's validation refuses such a port (tests/test_config.py); a port that got past
    it all the same ends the run with the daemon's own error, not a traceback."""
    import cv2

    from dffd.config import load_config
    from dffd.daemon.app import Daemon
    from dffd.exitcodes import EXIT_FAILURE

    clip = tmp_path / "clip.avi"  # a real frame source, opened before the link
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (160, 120))
    for _ in range(3):
        writer.write(np.full((120, 160, 3), 40, np.uint8))
    writer.release()
    path = tmp_path / "dffd.toml"
    path.write_text(
        '[camera]\ndriver = "visca"\nport = "/dev/ttyUSB0"\n'
        f'[capture]\nsource = "stream"\nurl = "{clip}"\n'
        f'[mqtt]\nembedded_port = {free_port()}\n[log]\ndir = "{tmp_path / "log"}"\n',
        encoding="utf-8",
    )
    config = load_config(path)
    config.camera.port = "visca-ip://"  # past the validation (assignment does not validate)
    daemon = Daemon(config, live_console=False)
    assert await daemon.main() == EXIT_FAILURE
    expected = "camera.port: 'visca-ip://' is not a camera port: it names no host"
    assert any(expected in r.getMessage() and r.levelname == "ERROR" for r in caplog.records)
