"""Daemon shell pieces that need no camera: estimator thread queue, rate meter, console view."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from rich.console import Console as RichConsole

from dffd.core.pipeline import PipelineOutput
from dffd.core.types import FrameTag
from dffd.daemon.app import EstimatorResult, EstimatorThread, RateMeter
from dffd.daemon.console import ConsoleSnapshot, render
from drivers.frames import Frame

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

    est = EstimatorThread(pipeline, deliver, queue_max=3)  # type: ignore[arg-type]
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
