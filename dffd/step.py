"""One core step: a tagged frame in, the core's output and the scheduler's feedback out.

The daemon's estimator thread, the lock-step bench and ``dffd replay`` all process frames with
:meth:`CoreStep.step`, so the estimates a user gets from the service are the ones the bench
scores and a replay reproduces. Pure and synchronous: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from dffd.core.pipeline import Pipeline, PipelineConfig, PipelineOutput

if TYPE_CHECKING:
    from dffd.core.lens import Lens
    from dffd.core.types import FrameTag
    from dffd.scheduler import Scheduler
    from drivers.frames import Frame

__all__ = ["CoreStep", "Feedback", "StepResult"]


@dataclass(frozen=True, slots=True)
class Feedback:
    """What the scheduler learns from one processed frame (``Scheduler.on_estimate``)."""

    t: float  # the frame's exposure mid-time
    sigma_m: float | None  # σ of the predicted depth while tracking
    plan: tuple[int, int, int] | None  # the next burst's focus counts (frames at known focus)
    centroid_px: tuple[float, float] | None  # the target's image centroid, if found
    pan_deg: float  # the head's pan/tilt during the exposure, from the tag
    tilt_deg: float

    def apply(self, scheduler: Scheduler) -> None:
        """Report this feedback to ``scheduler``."""
        scheduler.on_estimate(
            self.t,
            sigma_m=self.sigma_m,
            plan=self.plan,
            centroid_px=self.centroid_px,
            pan_deg=self.pan_deg,
            tilt_deg=self.tilt_deg,
        )


@dataclass(frozen=True, slots=True)
class StepResult:
    """One processed frame: the core's output and the scheduler's feedback."""

    frame_index: int
    tag: FrameTag
    output: PipelineOutput
    feedback: Feedback


class CoreStep:
    """The estimation core as every runner drives it, one tagged frame at a time."""

    def __init__(self, pipeline: Pipeline) -> None:
        self.pipeline = pipeline

    @classmethod
    def build(cls, config: PipelineConfig, lens: Lens) -> CoreStep:
        """A fresh core of ``config`` on ``lens``."""
        return cls(Pipeline(config, lens))

    def step(self, frame: Frame, tag: FrameTag) -> StepResult:
        """Process one frame exposed as ``tag`` says; the estimate (if any) and the feedback."""
        pipeline = self.pipeline
        # Every frame reaches the core, transit frames too, also while it acquires: a target
        # crossing the field of view fast (the paper-like circle at its near point, 7°/s) is
        # caught only on the frames of the start-up focus move. (Acquiring on stationary-focus
        # frames only, as the daemon once did, loses that target for good on the bench: ss
        # std 0.31 m instead of 7.7 mm with hil run paper-circle --fast.)
        out = pipeline.process(frame, tag)
        obs = out.observation
        centroid = None
        if obs is not None and obs.ok:
            centroid = (float(obs.centroid[0]), float(obs.centroid[1]))
        sigma: float | None = None
        plan: tuple[int, int, int] | None = None
        if pipeline.state == "tracking":
            pred = pipeline.predicted_depth()
            sigma = None if pred is None else pred[1]
            if tag.focus_counts is not None:
                plan = pipeline.plan_burst(tag.focus_counts)
        feedback = Feedback(frame.t, sigma, plan, centroid, tag.pan_deg, tag.tilt_deg)
        return StepResult(frame.index, tag, out, feedback)
