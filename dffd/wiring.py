"""One wiring: the service config turned into the core's and the scheduler's configuration.

The daemon, the lock-step bench, ``dffd replay`` and ``dffd calibrate`` all call these
builders, so a setting means the same thing in every runner (docs/design.md). A runner differs
only in where frames and time come from.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dffd.core.pipeline_config import PipelineConfig
from dffd.scheduler import SchedulerConfig, pixel_offset_to_deg
from dffd.step import SERVICE_TRACKERS, CoreStep
from drivers.visca.camera import profile_for

if TYPE_CHECKING:
    from collections.abc import Sequence

    from dffd.config import DffdConfig
    from dffd.config.models import CaptureSection
    from dffd.core.lens import Lens
    from dffd.core.tracking3d_types import TrackerKind
    from dffd.scheduler import Scheduler
    from drivers.frames import FrameSource
    from drivers.sim.config import SimCameraConfig
    from drivers.stream import StreamFrameSource

__all__ = [
    "WiringError",
    "arm_search",
    "build_core",
    "capture_latency_frames",
    "capture_source",
    "pipeline_config",
    "scheduler_config",
    "sim_camera_config",
    "stream_source",
]


# Frames waiting between the capture thread and the loop (drop-oldest beyond): the estimator
# wants the newest frame; two absorb one slow loop iteration.
CAPTURE_QUEUE_FRAMES = 2


class WiringError(ValueError):
    """The configuration names something that cannot be built; the message says what to do."""


def build_core(
    settings: DffdConfig, lens: Lens, trackers: Sequence[TrackerKind] = SERVICE_TRACKERS
) -> CoreStep:
    """The service's estimation core on ``lens``, holding ``[target] roi`` if one is given.

    ``trackers``: the 3D tracker kinds it runs (the first is published); the bench runs all.
    """
    core = CoreStep.build(pipeline_config(settings), lens, trackers)
    if settings.target.roi is not None:
        core.pipeline.acquire_roi(*settings.target.roi)
    return core


def arm_search(scheduler: Scheduler, settings: DffdConfig, t: float) -> None:
    """Arm ``scheduler``'s search sweep for the start of a run at ``t``, as ``[target]`` says.

    Automatic acquisition (no ``[target] roi``) sweeps pan/tilt when nothing is seen for
    ``[scheduler] search_after_s``; an ROI names a target in this view, so no sweep until it was
    seen and lost. The daemon and the lock-step bench both start this way, so a bench run
    searches exactly as the service would.
    """
    if settings.target.roi is None:
        scheduler.arm_search(t)
    else:
        scheduler.disarm_search()


def capture_latency_frames(capture: CaptureSection, fps: float) -> int:
    """Frames between an exposure and its delivery, as the scheduler counts them (whole frames,
    rounded up): ``[capture] latency_s`` at the camera's frame rate when it is set (a stream's
    measured delay: several frames), else ``latency_frames``."""
    if capture.latency_s is None:
        return capture.latency_frames
    # (a hair below a whole number of frames is that number: 0.1 s at 30 fps is 3, not 4)
    return max(math.ceil(capture.latency_s * fps - 1e-9), 0)


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
    """The scheduler configuration from ``[scheduler]``/``[capture]``/``[camera]`` (the pan/tilt
    speed tables from the profile of ``[camera] model``) and the facts of the running camera (its
    frame rate, exposure, focus speed, lens and frame size).

    ``baudrate`` defaults to ``[camera] baudrate``.
    """
    sc = settings.scheduler
    sigma_policy = sc.burst_policy == "sigma"
    exposure = None if exposure_s is None else min(exposure_s, 1.0 / fps)
    profile = profile_for(settings.camera.model)
    return SchedulerConfig(
        fps=fps,
        exposure_s=exposure,
        capture_latency_frames=capture_latency_frames(settings.capture, fps),
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
        # The speed tables of the [camera] model, from the driver's profile.
        pan_speeds_deg_s=profile.pan_speeds_deg_s,
        tilt_speeds_deg_s=profile.tilt_speeds_deg_s,
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
        # The search sweep over the [camera] model's pan/tilt range (dffd.scheduler.search).
        search_after_s=sc.search_after_s if sc.search_after_s > 0 else None,
        search_retry_s=sc.search_retry_s,
        pan_range_deg=profile.pan_range_deg,
        tilt_range_deg=profile.tilt_range_deg,
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
        focus_measure=est.focus_measure,
        vertex_response=est.vertex_response,
    )


def capture_source(settings: DffdConfig) -> FrameSource:
    """The OpenCV frame source of ``[capture]``: a v4l2 device or a network stream / file."""
    from drivers.capture import CaptureSettings, OpenCVFrameSource

    cap = settings.capture
    if cap.source == "stream":
        assert cap.url is not None  # validated: stream needs a url
        return stream_source(settings, cap.url)
    assert cap.device is not None  # validated: v4l2 needs a device
    capture = CaptureSettings(
        device=cap.device,
        width=cap.width,
        height=cap.height,
        fps=cap.fps,
        fourcc=cap.fourcc,
        buffer_size=1,  # one driver buffer: read() returns a fresh frame, not a stale one
        gray=True,  # the estimator's input
        queue_frames=CAPTURE_QUEUE_FRAMES,
        latency_s=cap.latency,
    )
    return OpenCVFrameSource(capture)


def stream_source(settings: DffdConfig, url: str) -> StreamFrameSource:
    """The FFmpeg stream source reading ``url`` with ``[capture]``'s rate, latency and timeouts."""
    from drivers.stream import StreamFrameSource, StreamSettings

    cap = settings.capture
    return StreamFrameSource(
        StreamSettings(
            url=url,
            fps=cap.fps,
            gray=True,  # the estimator's input
            queue_frames=CAPTURE_QUEUE_FRAMES,
            latency_s=cap.latency,
            timestamps=cap.timestamps,
            open_timeout_s=cap.open_timeout_s,
            read_timeout_s=cap.read_timeout_s,
        )
    )


def sim_camera_config(settings: DffdConfig) -> SimCameraConfig:
    """The simulated camera of ``[sim] camera_config`` looking at ``[sim] scenario``'s world."""
    from drivers.sim.config import SimConfigError, load_sim_camera_config, with_overrides
    from drivers.sim.resources import reference_camera_file

    sim = settings.sim
    path = sim.camera_config or reference_camera_file()
    target, trajectory = _scenario_world(sim.scenario_file)
    trajectory = {**trajectory, "seed": sim.seed}
    if sim.start_phase_deg is not None:
        trajectory["phase_deg"] = sim.start_phase_deg
    try:
        base = load_sim_camera_config(path)
        overrides: dict[str, Any] = {
            "seed": sim.seed,
            "world.target": target,
            "world.trajectory": trajectory,
            "capture.fps": settings.capture.fps,
        }
        return with_overrides(base, overrides)
    except SimConfigError as exc:
        raise WiringError(f"sim.camera_config / sim.scenario: {exc}") from exc


def _scenario_world(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``[target]`` and ``[trajectory]`` tables of a world TOML (drivers/sim/data/worlds/).

    The tables are validated by the
    simulator's own config types (``drivers.sim.config.WorldConfig``) when applied.
    """
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise WiringError(
            f"sim.scenario: cannot read {path}: {exc.strerror}; give a scenario name "
            "(static, approach, paper-circle, figure-eight, random) or a TOML file path"
        ) from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise WiringError(f"sim.scenario: {path} is not valid TOML: {exc}") from exc
    target = data.get("target", {})
    trajectory = data.get("trajectory")
    if not isinstance(trajectory, dict) or not isinstance(target, dict):
        raise WiringError(
            f"sim.scenario: {path} needs a [trajectory] table (and optionally [target]) "
            "with the keys of drivers/sim/config.py TrajectoryConfig/TargetConfig"
        )
    return target, trajectory
