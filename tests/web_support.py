"""In-process implementations of ``DashboardSource`` for the web tests.

``SyntheticDaemon``: a real Pipeline on synthetic disc frames in its own thread (the estimator
thread of the real daemon in miniature), results handed to the event loop, commands through the
real ``Publisher.execute`` path. ``StaticSource``: fixed numbers, for exact ``/metrics`` checks.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from pydantic import ValidationError

from dffd.config import DffdConfig
from dffd.core.pipeline import Measurement as CoreMeasurement
from dffd.core.pipeline import Pipeline, PipelineOutput
from dffd.core.synthetic import DiscScene, StreamStep, closed_loop, synthetic_lens
from dffd.core.tracking3d_types import Track3DEstimate
from dffd.mqtt import models
from dffd.mqtt.commands import CommandRejected
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics
from dffd.step import CoreStep
from dffd.web.interface import (
    DashboardFeed,
    EstimatePoint,
    FrameView,
    Snapshot,
    overlay_from_output,
)
from dffd.web.metrics import Metrics
from dffd.wiring import pipeline_config

FPS = 20.0  # synthetic frame rate: enough motion for the video, light on a shared 2-core box
WIDTH, HEIGHT = 320, 240
STOP_TIMEOUT_S = 2.0  # the frame thread finishes its current frame (a few ms) and exits
RATE_WINDOW_S = 5.0


def trajectory(t: float) -> tuple[float, float, float]:
    """A disc (~80 px wide) swinging in depth between 4.5 and 5.5 m, a little sideways."""
    return (0.01 * math.sin(0.7 * t), 0.0, 5.0 + 0.5 * math.sin(0.5 * t))


class SyntheticDaemon:
    """A running Pipeline on synthetic frames behind the DashboardSource protocol."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.lens = synthetic_lens()
        self.config = replace(pipeline_config(DffdConfig()), search_px=8)
        self.pipeline = Pipeline(self.config, self.lens)
        self.core = CoreStep(self.pipeline)  # the 3D tracker on top, as the daemon runs it
        self.scene = DiscScene(width=WIDTH, height=HEIGHT)
        self.feed = DashboardFeed()
        self.metrics = Metrics(self.snapshot)
        self.publisher = Publisher(
            PublisherSettings(host="127.0.0.1", port=1), Topics("dffd", "web-test"),
            on_command=self._on_command,
        )  # fmt: skip
        self.lock = threading.Lock()
        self.stop_event = threading.Event()
        self.state = "acquiring"
        self.roi: tuple[int, int, int, int] | None = None
        self.acquires: list[tuple[int, int, int, int]] = []
        self.frames_seen = 0
        self.frames_flowing = asyncio.Event()  # set after the first few frames
        self.seq = 0
        self.bursts = {"accepted": 0, "rejected": 0}
        self._frames: deque[float] = deque(maxlen=1000)
        self._estimates: deque[float] = deque(maxlen=1000)
        self._depths: deque[float] = deque(maxlen=1000)
        self._last_estimate: float | None = None
        self._thread = threading.Thread(target=self._run, name="web-test-estimator", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self._thread.join(STOP_TIMEOUT_S)

    # -- DashboardSource ---------------------------------------------------------------------
    def latest_frame(self) -> FrameView | None:
        return self.feed.latest_frame()

    def snapshot(self) -> Snapshot | None:
        now = time.monotonic()
        status = models.Status(
            availability="online",
            t=models.wall_time(),
            t_mono=now,
            state=self.state,  # type: ignore[arg-type]
            camera="web-test",
            rates=models.Rates(
                frame_hz=_rate(self._frames, now),
                estimate_hz=_rate(self._estimates, now),
                depth_hz=_rate(self._depths, now),
                depth_limit_hz=FPS / 7,
            ),
            link=models.LinkHealth(connected=True),
            mqtt=self.publisher.health(),
            drops=models.Drops(),
            version="test",
        )
        age = None if self._last_estimate is None else now - self._last_estimate
        return Snapshot(
            status, age, self.bursts["accepted"], self.bursts["rejected"], (WIDTH, HEIGHT)
        )

    def estimates_after(self, seq: int) -> Sequence[EstimatePoint]:
        return self.feed.estimates_after(seq)

    def rejections(self) -> Sequence[models.Measurement]:
        return self.feed.rejections()

    async def execute(self, payload: bytes) -> models.CommandReply:
        return await self.publisher.execute(payload)

    # -- the command handler (as the daemon's) --------------------------------------------------
    async def _on_command(self, command: models.Command) -> dict[str, Any] | None:
        if isinstance(command, models.Acquire):
            x, y, w, h = command.roi
            if x + w > WIDTH or y + h > HEIGHT:
                raise CommandRejected(f"roi {list(command.roi)} extends beyond the frame")
            with self.lock:
                self.pipeline.acquire_roi(x, y, w, h)
            self.roi = (x, y, w, h)
            self.acquires.append(self.roi)
            return {"roi": [x, y, w, h]}
        if isinstance(command, models.Release):
            with self.lock:
                self.pipeline.release()
            return None
        if isinstance(command, models.SetKnownSize):
            with self.lock:
                self.pipeline.set_known_size(command.size_m)
            return {"size_m": command.size_m}
        if isinstance(command, models.Home):
            return None
        if isinstance(command, models.SetBurstPolicy):
            return {"policy": command.policy}
        raise CommandRejected(f"unsupported command {command!r}")

    # -- the frame thread ------------------------------------------------------------------------
    def _run(self) -> None:
        t0 = time.monotonic()
        steps = closed_loop(
            self.pipeline, self.scene, self.lens, trajectory, fps=FPS, duration_s=3600.0
        )
        for step in steps:
            if self.stop_event.is_set():
                return
            c0 = time.thread_time()
            with self.lock:
                res = self.core.step(step.frame, step.tag)
            out, plan, track = res.output, res.feedback.plan, res.track
            cpu = time.thread_time() - c0
            exposed = time.monotonic()
            self.loop.call_soon_threadsafe(self._on_result, step, out, plan, track, cpu, exposed)
            # Pacing to the frame rate (a camera's clock), not waiting for a result.
            delay = t0 + (step.frame.index + 1) / FPS - time.monotonic()
            if self.stop_event.wait(max(0.0, delay)):
                return

    def _on_result(
        self,
        step: StreamStep,
        out: PipelineOutput,
        plan: tuple[int, int, int] | None,
        track: Track3DEstimate | None,
        cpu_s: float,
        exposed: float,
    ) -> None:
        now = time.monotonic()
        self.frames_seen += 1
        if self.frames_seen >= 5:
            self.frames_flowing.set()
        self._frames.append(now)
        self.state = out.state
        self.metrics.observe_frame_cpu(cpu_s)
        est = out.estimate
        self.feed.add_frame(
            FrameView(
                step.frame.index,
                step.frame.t,
                step.frame.image,
                overlay_from_output(
                    out,
                    normal_half_px=float(self.config.search_px),
                    focus_counts=step.tag.focus_counts,
                    bracket_counts=plan,
                    counts_range=self.lens.counts_range,
                    roi=self.roi,
                ),
            )
        )
        m = out.measurement
        if m is not None:
            self.bursts["accepted" if m.accepted else "rejected"] += 1
            self._depths.append(now)
            with contextlib.suppress(ValidationError):  # a burst cut short has < 3 frames
                self.feed.add_measurement(self._measurement(m))
        if est is not None:
            self.seq += 1
            self._estimates.append(now)
            self._last_estimate = now
            d = {k: _fin(est.depth_m.get(k)) for k in ("measured", "cf1", "cf2", "lpv", "kf")}
            payload = models.Estimate(
                seq=self.seq,
                t=models.wall_time(),
                t_mono=step.frame.t,
                state=est.state,
                depth_m=models.DepthByEstimator(**d),
                best=est.best,
                z_m=_fin(est.z_m),
                sigma_m=_fin(est.sigma_m),
                size_m=_fin(est.size_m),
                r_px=_fin(est.r_px),
                position_m=track.position_m if track else None,
                velocity_m_s=track.velocity_m_s if track else None,
                acceleration_m_s2=track.acceleration_m_s2 if track else None,
                angular_speed_rad_s=track.angular_speed_rad_s if track else None,
                position_sigma_m=track.position_sigma_m if track else None,
                model_probabilities=dict(track.model_probabilities) if track else None,
                pan_deg=0.0,
                tilt_deg=0.0,
            )
            self.feed.add_estimate(payload, truth_z_m=step.truth_m[2])
            self.metrics.observe_publish_latency(now - exposed)

    def _measurement(self, m: CoreMeasurement) -> models.Measurement:
        return models.Measurement(
            seq=self.bursts["accepted"] + self.bursts["rejected"],
            burst=m.burst_id,
            t=models.wall_time(),
            t_mono=m.t,
            focus_counts=list(m.focus_counts),
            costs=[max(0.0, c) for c in m.costs],
            fit=models.Fit(
                alpha=_fin(m.alpha),
                v_mm=_fin(m.v_hat_mm),
                residual=_fin(m.residual),
                accepted=m.accepted,
                reason=m.reason or None,
            ),
            z_m=_fin(m.z_m),
        )


class StaticSource:
    """Fixed figures, so a ``/metrics`` scrape can be checked number by number."""

    def __init__(self) -> None:
        self.status = models.Status(
            availability="online",
            t=1.0,
            t_mono=2.0,
            state="tracking",
            camera="static",
            rates=models.Rates(frame_hz=29.5, estimate_hz=21.25, depth_hz=2.5, depth_limit_hz=3.75),
            link=models.LinkHealth(
                connected=True, errors=3, timeouts=4, reconnects=5, replies=600,
                last_reply_age_s=0.02,
            ),
            mqtt=models.MqttHealth(connected=False, reconnects=6, published=700, backlog=42),
            drops=models.Drops(frames=7, publish_queue=8, backlog=9, log=10),
            version="test",
        )  # fmt: skip
        self.replies: list[bytes] = []

    def latest_frame(self) -> FrameView | None:
        return None

    def snapshot(self) -> Snapshot | None:
        return Snapshot(self.status, 0.25, 11, 12, (640, 480))

    def estimates_after(self, seq: int) -> Sequence[EstimatePoint]:
        return []

    def rejections(self) -> Sequence[models.Measurement]:
        return []

    async def execute(self, payload: bytes) -> models.CommandReply:
        self.replies.append(payload)
        return models.CommandReply(id=None, ok=True, t=models.wall_time())


def _rate(times: deque[float], now: float) -> float:
    recent = [t for t in times if now - t <= RATE_WINDOW_S]
    if len(recent) < 2:
        return 0.0
    return (len(recent) - 1) / max(1e-6, recent[-1] - recent[0])


def _fin(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)
