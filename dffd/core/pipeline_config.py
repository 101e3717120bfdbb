"""The estimation pipeline's parameters: the ones a runner sets, and the fixed ones.

:class:`PipelineConfig` is what :class:`dffd.core.pipeline.Pipeline` is built with (set from the
service configuration by :func:`dffd.wiring.pipeline_config`); the constants are the values its
steps use that no configuration changes, each with where it comes from.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field
from typing import Literal

from dffd.core.contour import TrackerConfig
from dffd.core.filters import KFNoise
from dffd.core.focus import FitConfig, PlanConfig
from dffd.core.noise import NoiseAdaptConfig
from dffd.core.outputs import EstimatorName
from dffd.literals import FocusMeasure

__all__ = [
    "ACQUIRE_DOWNSCALE",
    "REACQUIRE_VELOCITY_GAP_S",
    "SIZE_EDGE_WIDTHS",
    "SIZE_HISTORY_FRAMES",
    "SIZE_JUMP_MAX_BLUR_PX",
    "SIZE_JUMP_MAX_GAP_S",
    "PipelineConfig",
]

# Sizes kept for the burst compensation and the transport of a burst's depth: ~8.5 s at 30 fps,
# more than a rolling burst's span (rolling_max_span_s) plus the wait for its tracking frame.
SIZE_HISTORY_FRAMES = 256
# A frame gives a size when its edge profile, this many log-parabola widths, fits in the normal
# lines (±search_px): wider (the full-range brackets' outer frames, fast focus transits) the
# curvature correction of r fails (synthetic discs of 20/40 px: r −0.05…−0.56 px at widths of
# 4.1–5.6 px, < 0.01 px up to 3.3 px; docs/estimation.md §11).
SIZE_EDGE_WIDTHS = 3.0
# A size off the track is a jump only within this time of the last used size (s): further, the
# filtered rate's prediction is too uncertain (a rolling bracket's track frames are ~0.2 s apart).
SIZE_JUMP_MAX_GAP_S = 0.5
# A tracking frame is tested for a jump only within this blur radius (px) of the predicted
# depth's sharp setting: half the bracket ends' blur (PlanConfig.outer_blur_px, 3 px), whose
# sizes were 3-35 % off. Tracking frames sit at the plan's middle (< 0.75 px: the scheduler
# re-focuses beyond a quarter of a bracket step); a frame held at a bracket end is not one.
SIZE_JUMP_MAX_BLUR_PX = 1.5
# The whole-frame acquisition search runs on a copy this many times smaller per axis (area
# averaged): it was ~70 % of an acquisition frame's CPU at full size on 640×480 (blur, Otsu and
# contours over the whole frame); ContourTracker.start refines the coarse polygon at full size.
ACQUIRE_DOWNSCALE = 2
# A target re-acquired at most this long (s) after its last sighting starts its contour with the
# velocity between the two sightings; an older sighting says little of where it goes now (the
# scheduler's rule for the head's velocity, dffd.scheduler.head.MAX_VELOCITY_GAP_S: the core
# does not import the scheduler).
REACQUIRE_VELOCITY_GAP_S = 0.5


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Estimation parameters (defaults documented in docs/estimation.md)."""

    n_normals: int = 64  # Nl of (2)
    search_px: int = 12  # half-length of the normal lines
    settle_s: float = 5.0  # settling time: steady-state statistics start after it
    burst_size: int = 3  # frames of a complete burst
    # Rolling bursts: the previous end must be at most this old (s) to close a burst with.
    rolling_max_span_s: float = 2.0
    # image scale: "pinhole" f/p (docs/design.md §3.4, the reference simulator) or "thin_lens" v0/p
    # (chief ray; lenses whose image size "breathes" with focus)
    magnification: Literal["thin_lens", "pinhole"] = "pinhole"
    transport_measurements: bool = True
    # Burst motion compensation: the target's sharp setting moves during a burst (~0.6 s; at
    # 0.25 m/s and 8 m that is ~2 µm of v against ~0.6 µm of fit noise). The size ratio gives
    # each frame's depth relative to the burst mid-time, z_i = z s(t_mid)/s(t_i), so every focus
    # setting is shifted by v(z_i) − v(z) before the fit (docs/estimation.md).
    compensate_burst_motion: bool = True
    # Head motion in the contour's prediction: the image motion of the head's own turn between
    # two frames (their tags' pan/tilt) is added to the target's (ContourTracker.update), and a
    # target re-acquired within REACQUIRE_VELOCITY_GAP_S of its last sighting starts with the
    # velocity between the two (ContourTracker.seed_velocity). Off: the image motion alone.
    compensate_head_motion: bool = True
    plan_lead_s: float = 0.3  # plan → burst mid-time (slots at ~0, 0.2, 0.6 s at 30 fps)
    # CF1 / CF2 (Lemma 1 from the noise densities)
    cf1_k: float = 1.0  # rad/s
    cf2_nominal_size_m: float | None = None  # None: mean of the first size measurements
    cf2_size_bursts: int = 10  # ... over this many accepted bursts, then frozen (paper: fixed R)
    # Start-up hand-over: the fixed-gain filters (CF1, CF2, LPV) are seeded from the KF (the LPV
    # with both of its states, which mean the same as the KF's) at each accepted burst while the
    # KF converges; a fixed-gain observer with the narrow steady bandwidth would need several
    # 1/λ ≈ 8 s to forget a start-up error. None: online, while the KF's error still costs the
    # LPV less than at the previous burst (EstimatorBank._seeding, docs/estimation.md §19); a
    # number: that many accepted bursts (20 before §19, swept on our simulator in §7).
    warmup_bursts: int | None = None
    # Effective time of a depth measurement relative to the mean exposure mid-time of its frames
    # (z_m equals z(t_b + τ)): this fixed part (0: the exposure timing) plus τ̂ estimated online
    # from the innovations (noise_adapt; docs/estimation.md §9). It was a constant 0.03 s fitted
    # to the reference simulator's lean (−13 ms on a held-out lens).
    measurement_time_offset_s: float = 0.0
    # Measurement noise and time offset adapted from the innovations; honest σ per estimator
    noise_adapt: NoiseAdaptConfig = field(default_factory=NoiseAdaptConfig)
    # LPV observer: error poles and the declared ρ range of the gain schedule
    # rad/s: the transported z_m steps once a burst (~1 s) with ~0.5 % noise while ρ is nearly
    # noise-free, so the observer should average ~10 bursts (decay 0.12/s; measured on the
    # reference simulator: ω 0.6 → 0.15 takes LPV from 0.88x to 0.45x of raw z_m's std)
    lpv_omega: float = 0.15
    lpv_zeta: float = 0.8
    kf_noise: KFNoise = field(default_factory=KFNoise)
    differentiator_omega: float = 12.0  # rad/s, bandwidth of ṙ and of the velocity
    # ψ_m for CF1/CF2: "step" = exact size difference over each step (its noise telescopes when
    # the filter integrates it, and it has no lag); "differentiator" = the filtered ṙ (lags 2ζ/ω)
    psi_source: Literal["step", "differentiator"] = "step"
    max_gap_s: float = 2.0  # estimators restart after a gap without tracking longer than this
    # A depth jump: ln s of a frame off the filtered rate's prediction by more than this (the
    # per-frame size noise is 0.03-0.05 %, a jitter-lost-and-found target or another target 40x
    # that). No burst is fitted and no depth transported across it (docs/estimation.md §11).
    size_jump_ln: float = 0.02
    # Size offset s_m = R/z + δ p/F (dffd.core.sizes.SizeOffset): the prior σ of δ in px; None
    # leaves it out (the default: not yet validated on the bench, docs/estimation.md §11).
    size_offset_prior_px: float | None = None
    auto_acquire: bool = True
    reacquire_every_frames: int = 5  # whole-frame search period while lost (it costs ~ms)
    motion: Literal["similarity", "affine"] = "similarity"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)
    # Set from the service config ([estimators], [target]) by dffd.wiring.pipeline_config, which
    # is where their defaults live: no second default here that a runner could drift onto.
    _: KW_ONLY
    best: EstimatorName
    known_size_m: float | None  # enables CF1
    cf2_sigma_psi: float  # m/s/√Hz (CF2, Lemma 1 from the noise densities)
    cf2_sigma_beta: float  # m/s²/√Hz
    cf2_sigma_z: float  # m·√s
    rho_min: float  # 1/s: ρ = ṙ/r = −ż/z; ±2/s covers 4 m/s at 2 m
    rho_max: float
    # Focus measure of a burst frame (dffd.core.focus.frame_cost): "peak_gradient" is the
    # paper's cost (2); "edge_variance" holds for any PSF but is noisier (docs/estimation.md §8).
    focus_measure: FocusMeasure
    # Correct each burst's vertex by the lens file's measured vertex response (when it has one
    # for this measure; docs/estimation.md §21).
    vertex_response: bool
