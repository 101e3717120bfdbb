"""What the estimation core hands out: burst measurements, per-frame estimates, their wrapper.

Shared by the pipeline's parts (:mod:`dffd.core.bursts` builds a :class:`Measurement`,
:mod:`dffd.core.pipeline` the rest) and re-exported by :mod:`dffd.core.pipeline`, the public
entry point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from dffd.core.contour import BoundaryObservation

__all__ = [
    "ESTIMATORS",
    "Estimate",
    "EstimatorName",
    "Measurement",
    "PipelineOutput",
    "TrackState",
    "Vec3",
]

TrackState = Literal["idle", "acquiring", "tracking", "lost"]
EstimatorName = Literal["measured", "cf1", "cf2", "lpv", "kf"]
ESTIMATORS: tuple[EstimatorName, ...] = ("measured", "cf1", "cf2", "lpv", "kf")
Vec3 = tuple[float, float, float]


# Not frozen, to be treated as read-only (as Estimate below): a frozen dataclass sets each
# field through object.__setattr__ (~0.15 µs a field on the 2-core machine), one per burst.
@dataclass(slots=True)
class Measurement:
    """One burst: settings, costs, parabola fit and the depth measurement (``…/measurement``)."""

    burst_id: int
    t: float  # mid-time of the burst frames
    frame_indices: tuple[int, ...]
    focus_counts: tuple[int, ...]
    v_mm: tuple[float, ...]
    costs: tuple[float, ...]
    cost_sigmas: tuple[float, ...]
    alpha: float
    v_hat_mm: float
    residual: float
    accepted: bool
    reason: str
    z_m: float | None
    sigma_m: float | None


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__ (~1 µs a field on the 2-core machine), and one is built on every frame.
@dataclass(slots=True)
class Estimate:
    """Everything known at one frame with a contour (``…/estimate``)."""

    frame_index: int
    t: float
    state: TrackState
    depth_m: dict[str, float | None]  # measured, cf1, cf2, lpv, kf
    measured_t: float | None  # burst mid-time of ``depth_m["measured"]``
    best: EstimatorName
    z_m: float | None  # the best estimator's depth
    sigma_m: float | None
    beta_m_s: float | None  # CF2 bias estimate β̂
    lpv_b_m_s: float | None  # LPV disturbance estimate
    size_m: float | None  # R̂ = ẑ s
    r_px: float
    rho: float | None  # ṙ/r over the last step, 1/s
    centroid_px: tuple[float, float]
    position_m: Vec3 | None  # camera frame
    velocity_m_s: Vec3 | None
    position_world_m: Vec3 | None
    velocity_world_m_s: Vec3 | None
    pan_deg: float
    tilt_deg: float
    focus_counts: int | None
    inlier_fraction: float
    # σ per estimator (measured, cf1, cf2, lpv, kf; None where it has no value); sigma_m is the
    # best's. Honest σ: adapted noise, correlated measurements, Student-t start-up factor.
    sigma_by: dict[str, float | None] = field(default_factory=dict)


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__ (~1 µs a field on the 2-core machine), and one is built on every frame.
@dataclass(slots=True)
class PipelineOutput:
    """Result of one :meth:`Pipeline.process` call."""

    state: TrackState
    estimate: Estimate | None
    measurement: Measurement | None
    observation: BoundaryObservation | None
    # While acquiring: the visible centroid of a target cut by the frame's edge, where the head
    # should turn (dffd/core/clipped.py); None otherwise.
    candidate_px: tuple[float, float] | None = None
