"""One wiring: the service config turned into the core's and the scheduler's configuration.

The daemon, the lock-step bench, ``dffd replay`` and ``dffd calibrate`` all call these
builders, so a setting means the same thing in every runner (docs/design.md). A runner differs
only in where frames and time come from.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from dffd.core.pipeline import PipelineConfig
from dffd.scheduler import SchedulerConfig, pixel_offset_to_deg
from dffd.step import CoreStep

if TYPE_CHECKING:
    from dffd.config import DffdConfig
    from dffd.core.lens import Lens

__all__ = ["build_core", "pipeline_config", "scheduler_config"]


def build_core(settings: DffdConfig, lens: Lens) -> CoreStep:
    """The service's estimation core on ``lens``, holding ``[target] roi`` if one is given."""
    core = CoreStep.build(pipeline_config(settings), lens)
    if settings.target.roi is not None:
        core.pipeline.acquire_roi(*settings.target.roi)
    return core


def scheduler_config(
    settings: DffdConfig,
    *,
    fps: float,
    exposure_s: float | None,
    focus_speed_counts_per_s: float,
    focal_length_mm: float,
    pixel_pitch_mm: float,
    frame_size: tuple[int, int],
    baudrate: int | None = None,
) -> SchedulerConfig:
    """The scheduler configuration from ``[scheduler]``/``[capture]``/``[camera]`` and the facts
    of the running camera (its frame rate, exposure, focus speed, lens and frame size).

    ``baudrate`` defaults to ``[camera] baudrate``.
    """
    sc = settings.scheduler
    sigma_policy = sc.burst_policy == "sigma"
    exposure = None if exposure_s is None else min(exposure_s, 1.0 / fps)
    return SchedulerConfig(
        fps=fps,
        exposure_s=exposure,
        capture_latency_frames=math.ceil(settings.capture.latency_frames),
        timing_margin_s=sc.timing_margin_s,
        burst_mode=sc.burst_mode,
        # sigma policy: a burst when σ of ẑ exceeds the threshold, and otherwise only after
        # sigma_max_interval_frames (so a filter that under-reports σ cannot starve it).
        burst_every_frames=sc.sigma_max_interval_frames if sigma_policy else (
            sc.burst_every_n_frames
        ),
        sigma_trigger_m=sc.sigma_threshold_m if sigma_policy else None,
        focus_speed_counts_per_s=focus_speed_counts_per_s,
        baudrate=settings.camera.baudrate if baudrate is None else baudrate,
        focal_length_mm=focal_length_mm,
        pixel_pitch_mm=pixel_pitch_mm,
        frame_size=frame_size,
        pan_tilt_mode=sc.pan_tilt_mode,
        pan_tilt_gain_per_s=sc.pan_tilt_kp_per_s,
        pan_tilt_feedforward=sc.pan_tilt_feedforward,
        pan_tilt_lost_s=sc.pan_tilt_lost_s,
        pan_tilt_search_s=sc.pan_tilt_search_s,
        acquire_stable_frames=sc.acquire_stable_frames,
        pan_tilt_deadband_deg=pixel_offset_to_deg(
            sc.pan_tilt_deadband_px, focal_length_mm, pixel_pitch_mm
        ),
        pan_tilt_max_correction_deg_s=sc.pan_tilt_max_correction_deg_s,
        pan_tilt_min_interval_s=1.0 / sc.pan_tilt_max_command_hz,
    )  # fmt: skip


def pipeline_config(settings: DffdConfig) -> PipelineConfig:
    """The estimation core's configuration from ``[estimators]`` and ``[target]``."""
    est = settings.estimators
    return PipelineConfig(
        best=est.best,
        known_size_m=settings.target.known_size_m,
        cf2_sigma_psi=est.sigma_psi,
        cf2_sigma_beta=est.sigma_beta,
        cf2_sigma_z=est.sigma_z,
        rho_min=est.lpv_rho_min_per_s,
        rho_max=est.lpv_rho_max_per_s,
    )
