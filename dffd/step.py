"""One core step: a tagged frame in, the core's output, 3D tracks and scheduler feedback out.

The daemon's estimator thread, the lock-step bench and ``dffd replay`` all process frames with
:meth:`CoreStep.step`, so the estimates a user gets from the service are the ones the bench
scores and a replay reproduces. Pure and synchronous: no I/O, no clock.

Every frame with an estimate also steps the 3D trackers (:mod:`dffd.core.tracking3d`) on the
raw channels the depth filters fuse (:mod:`dffd.core.track_feed`): the target's direction and
image size on the frame, and each accepted burst's size measurement as the pipeline made it — not
the fused depth, whose errors are correlated from frame to frame (docs/tracking3d.md). The service
runs ``("mmae",)``; the bench adds ``"imm"`` and ``"cv"``.

The step also decides whether a frame's depths may be published (the first-depth gate,
:mod:`dffd.first_depth`): the daemon nulls the depth fields of an estimate it holds back, the
bench leaves it out of its scores and ``dffd replay`` out of its summary, so every runner counts
from the same first published estimate (docs/estimation.md §22).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from dffd.core.pipeline import Estimate, Pipeline, PipelineOutput
from dffd.core.pipeline_config import PipelineConfig
from dffd.core.track_feed import FeedFrame, SizeFeed
from dffd.core.tracking3d import Tracker3DBank
from dffd.core.tracking3d_camera import (
    CameraModel,
    DirectionDepth,
    cartesian_measurement,
    direction_rate_deg_s,
)
from dffd.core.tracking3d_types import Track3DEstimate, TrackerKind
from dffd.first_depth import FirstDepthGate

if TYPE_CHECKING:
    from dffd.core.lens import Lens
    from dffd.core.types import FrameTag
    from dffd.scheduler import Scheduler
    from drivers.frames import Frame

FloatArray = npt.NDArray[np.float64]
__all__ = ["SERVICE_TRACKERS", "CoreStep", "Feedback", "StepResult"]

# The 3D trackers the service runs: the multiple-model filter it publishes. The bench runs
# every kind (dffd.core.tracking3d.TRACKER_KINDS) to compare them on the same frames.
SERVICE_TRACKERS: tuple[TrackerKind, ...] = ("mmae",)


# Not frozen, to be treated as read-only (as StepResult below): built on every frame.
@dataclass(slots=True)
class Feedback:
    """What the scheduler learns from one processed frame (``Scheduler.on_estimate``)."""

    t: float  # the frame's exposure mid-time
    sigma_m: float | None  # σ of the predicted depth while tracking
    plan: tuple[int, int, int] | None  # the next burst's focus counts (frames at known focus)
    centroid_px: tuple[float, float] | None  # the target's image centroid, if found
    pan_deg: float  # the head's pan/tilt during the exposure, from the tag
    tilt_deg: float
    # The published 3D track's pan/tilt rate of the target's direction (deg/s), if a track.
    track_rate_deg_s: tuple[float, float] | None = None

    def apply(self, scheduler: Scheduler) -> None:
        """Report this feedback to ``scheduler``."""
        scheduler.on_estimate(
            self.t,
            sigma_m=self.sigma_m,
            plan=self.plan,
            centroid_px=self.centroid_px,
            pan_deg=self.pan_deg,
            tilt_deg=self.tilt_deg,
            track_rate_deg_s=self.track_rate_deg_s,
        )


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__ (~1 µs a field on the 2-core machine), and one is built on every frame.
@dataclass(slots=True)
class StepResult:
    """One processed frame: the core's output, the 3D tracks and the scheduler's feedback."""

    frame_index: int
    tag: FrameTag
    output: PipelineOutput
    feedback: Feedback
    # Each tracker kind's estimate at this frame (only on frames with an estimate, and only
    # kinds that hold a track); the first kind of the core's bank is the published one.
    tracks: Mapping[str, Track3DEstimate] = field(default_factory=dict)
    published_kind: str | None = None
    # Whether the estimate's depths (and every field that follows from them) may be published:
    # False while the first-depth gate holds them back (dffd.first_depth), and without estimate.
    published: bool = False

    @property
    def track(self) -> Track3DEstimate | None:
        """The published tracker's estimate at this frame, if any."""
        return None if self.published_kind is None else self.tracks.get(self.published_kind)


class CoreStep:
    """The estimation core as every runner drives it, one tagged frame at a time."""

    def __init__(
        self, pipeline: Pipeline, trackers: Sequence[TrackerKind] = SERVICE_TRACKERS
    ) -> None:
        self.pipeline = pipeline
        self.trackers = Tracker3DBank(trackers)
        self._feed = SizeFeed(next(iter(self.trackers.trackers.values())).config)
        self._camera: CameraModel | None = None
        self.gate = FirstDepthGate()  # no depth published before a bracketed, precise burst

    @classmethod
    def build(
        cls,
        config: PipelineConfig,
        lens: Lens,
        trackers: Sequence[TrackerKind] = SERVICE_TRACKERS,
    ) -> CoreStep:
        """A fresh core of ``config`` on ``lens`` running the 3D ``trackers``."""
        return cls(Pipeline(config, lens), trackers)

    def step(self, frame: Frame, tag: FrameTag) -> StepResult:
        """Process one frame exposed as ``tag`` says; the estimate (if any) and the feedback."""
        pipeline = self.pipeline
        # Every frame reaches the core, transit frames too, also while it acquires: a target
        # crossing the field of view fast (the paper-like circle at its near point, 7°/s) is
        # caught only on the frames of the start-up focus move. (Acquiring on stationary-focus
        # frames only, as the daemon once did, loses that target for good on the bench: ss
        # std 0.31 m instead of 7.7 mm with hil run paper-circle --fast.)
        out = pipeline.process(frame, tag)
        if out.measurement is not None:
            self.gate.on_measurement(out.measurement)
        depths_out = out.estimate is not None and self.gate.passes(out.estimate)
        obs = out.observation
        centroid = out.candidate_px  # while acquiring: a target cut by the frame's edge
        if obs is not None and obs.ok:
            centroid = (float(obs.centroid[0]), float(obs.centroid[1]))
        sigma: float | None = None
        plan: tuple[int, int, int] | None = None
        if pipeline.state == "tracking":
            pred = pipeline.predicted_depth()
            sigma = None if pred is None else pred[1]
            if tag.focus_counts is not None:
                plan = pipeline.plan_burst_for(tag.focus_counts, pred)
        tracks = self._track(frame, tag, out)
        published = tracks.get(self.trackers.kinds[0])
        rate = None if published is None else direction_rate_deg_s(published)
        feedback = Feedback(frame.t, sigma, plan, centroid, tag.pan_deg, tag.tilt_deg, rate)
        return StepResult(
            frame.index, tag, out, feedback, tracks, self.trackers.kinds[0], depths_out
        )

    def _track(
        self, frame: Frame, tag: FrameTag, out: PipelineOutput
    ) -> dict[str, Track3DEstimate]:
        """Step the 3D trackers on a tracking frame with an estimate (a new target forgets the
        track); other frames with an estimate get the tracks extrapolated to their time."""
        est = out.estimate
        if est is not None and est.measured_t is not None:
            # The frame applied a burst: the pipeline's size measurement (depth times the image
            # size at the burst's lean-corrected time, from its per-frame size history).
            size = self.pipeline.size_measurement
            if size is not None:
                self._feed.burst(*size)
        if est is None:
            if self.pipeline.state in ("idle", "acquiring"):
                self.trackers.reset()  # released, or told to acquire: the next target is new
                self._feed.reset()
            return {}
        if tag.role != "track":
            # Only a tracking frame (at the best focus) has an unbiased image size; elsewhere
            # the tracks are carried to the frame's time without a filter step (cheap).
            return self.trackers.extrapolate(est.t)
        if est.z_m is None or est.size_m is None or not est.z_m > 0.0:
            return self.trackers.step_size(est.t, None)  # no size yet: predict (if a track)
        # s = r·pitch/F of this frame; the pipeline publishes R̂ = ẑ s, so s = R̂/ẑ exactly.
        s = est.size_m / est.z_m
        feed = FeedFrame(est.t, est.centroid_px, est.pan_deg, est.tilt_deg, s)
        unit, size = self._feed.frame(feed, self._camera_for(frame))
        return self.trackers.step_size(est.t, unit, size)

    def _camera_for(self, frame: Frame) -> CameraModel:
        """The camera model of the frame's size (cached)."""
        h, w = frame.image.shape[:2]
        camera = self._camera
        if camera is None or camera.principal_point_px != ((w - 1) / 2.0, (h - 1) / 2.0):
            lens = self.pipeline.lens
            # The covariance's lateral part scales with pitch/image distance; the focal length
            # stands for the image distance (they differ by f/(z − f), ~3 % at 1 m): the lateral
            # σ are millimetres against a depth σ of centimetres.
            camera = self._camera = CameraModel.centred(
                (w, h), lens.pixel_pitch_mm, lens.focal_length_mm
            )
        return camera

    def fused_measurement(
        self, frame: Frame, est: Estimate
    ) -> tuple[FloatArray, FloatArray] | None:
        """The estimate's world position (fused depth) and its covariance; None without depth or
        σ — the trackers' input before the size feed, kept for comparison."""
        if est.position_world_m is None or est.z_m is None or est.sigma_m is None:
            return None
        camera = self._camera_for(frame)
        meas = DirectionDepth(
            est.centroid_px, est.pan_deg, est.tilt_deg, est.z_m, max(est.sigma_m, 1e-6)
        )
        _, cov = cartesian_measurement(meas, camera)
        # The position the pipeline published (its image distance at the frame's focus).
        return np.asarray(est.position_world_m, dtype=np.float64), cov
