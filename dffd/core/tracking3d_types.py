"""The 3D trackers' vocabulary: their kinds, state layout, configuration and output.

What :mod:`dffd.core.tracking3d` is configured with and returns, and what the core step, the
payloads, the replay and the bench name without stepping a tracker (world frame, SI units;
frames in ``docs/tracking3d.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from dffd.core.motion_models import (
    STATE_DIM,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    MotionModel,
)

Vec3 = tuple[float, float, float]
# The tracker's state: the motion models' 10 elements, then the target's size R (m) — the
# constant of the size invariant ``z s = R`` (docs/tracking3d.md). The models never touch it.
SIZE = STATE_DIM
TRACK_DIM = STATE_DIM + 1
TrackerKind = Literal["mmae", "imm", "cv"]
TRACKER_KINDS: tuple[TrackerKind, ...] = ("mmae", "imm", "cv")


@dataclass(frozen=True, slots=True)
class Tracker3DConfig:
    """Noise densities of the bank and the combination's constants.

    Values describe the paper's setting — a small indoor robot at walking pace (≤ 1 m/s) that
    turns and stops — not a fit to any simulator run.
    """

    q_cv_m2_s3: float = 1e-4  # bank CV (quiet): velocity wanders ~1 cm/s per √s
    q_cv_single_m2_s3: float = 1e-2  # lone CV baseline, absorbs manoeuvres: ~0.1 m/s per √s
    # The bank's CA, CT and turn-rate densities and burst_sigma_scale were swept on the
    # reference optics only (docs/tracking3d.md, "Noise densities"); the aberrated is held out.
    q_ca_m2_s5: float = 5e-2  # CA white jerk: acceleration wanders ~0.22 m/s² per √s
    # CT white acceleration (on top of the turn), as quiet as the CV: a quieter CT (swept
    # 1e-5, 3e-5, 1e-4) wins the probability on a straight line, where ω = 0 makes it a CV.
    q_ct_m2_s3: float = 1e-4
    q_omega_rad2_s3: float = 1e-6  # CT turn-rate random walk: ~0.001 rad/s per √s
    probability_floor: float = 1e-3  # MMAE: no model probability below this
    switch_rate_hz: float = 0.2  # IMM: rate of leaving a model (mean sojourn 5 s)
    init_sigma_v_m_s: float = 1.0  # prior on the velocity at the first measurement
    init_sigma_a_m_s2: float = 0.5
    init_sigma_omega_rad_s: float = 0.3
    max_gap_s: float = 1.0  # a longer gap between measurements restarts the track
    # Size-state measurements (step_size): random walk of the target size R. R is constant for a
    # rigid target; the walk lets it follow what the size invariant does not model (a flat
    # target seen at a changing angle, a residual magnification error): 10⁻⁶ m (3·10⁻⁵ of a
    # 36 mm target) per √s (swept 0, 10⁻¹³, 10⁻¹², 10⁻¹¹ on the reference optics).
    q_size_m2_s: float = 1e-12
    # A track starts only on a burst size this precise (σ_R/R, after burst_sigma_scale). With a
    # vaguer size the pseudo-measurement p − R m = 0 drags R̂ and p together towards 0 (its
    # noise R̂² Σ_m shrinks with them): the start-up bursts spanning the working range measure R
    # to 9-18 % and put the track metres off (stop-and-go, reference optics).
    start_size_sigma_rel: float = 0.01
    # Measurement noise of the size-state feed (dffd.core.track_feed). Measured on the reference
    # optics only (hil run --optics reference, steady state, against the simulator's truth):
    sigma_size_rel: float = 3e-4  # σ of s/s on tracking frames (R = s·z_true scatters 2·10⁻⁴)
    sigma_px: float = 0.3  # centroid σ per axis
    sigma_angle_deg: float = 0.03  # pan/tilt of the tag (dead-reckoned head model) per axis
    # The pipeline's size measurements' errors are 2.0-2.5 of their σ with lag-1
    # autocorrelation 0.3-0.5 (rolling bursts share frames), which a white-noise update
    # over-trusts: 3.
    burst_sigma_scale: float = 3.0

    def bank(self) -> list[MotionModel]:
        """The multiple-model bank: CV, CA, CT."""
        return [
            ConstantVelocity(self.q_cv_m2_s3),
            ConstantAcceleration(self.q_ca_m2_s5),
            CoordinatedTurn(self.q_ct_m2_s3, self.q_omega_rad2_s3),
        ]


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__ (~1 µs a field on the 2-core machine), and one is built on every frame.
@dataclass(slots=True)
class Track3DEstimate:
    """The tracker's output at one time (world frame, SI units)."""

    t: float
    position_m: Vec3
    velocity_m_s: Vec3
    acceleration_m_s2: Vec3
    angular_speed_rad_s: float  # about the upward vertical, + = counter-clockwise from above
    position_sigma_m: Vec3  # √diag of the combined position covariance
    model_probabilities: dict[str, float] = field(default_factory=dict)
