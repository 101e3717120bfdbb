"""One wiring: the daemon, the bench and ``dffd replay`` configure the core and the scheduler
from the service config with the same functions."""

from __future__ import annotations

import dataclasses

from dffd.config import DffdConfig
from dffd.wiring import pipeline_config, scheduler_config
from drivers.visca.camera import EVI_D70, EVI_D100
from hil.lockstep import pipeline_config as bench_pipeline_config
from hil.scenario import load_scenario


def test_scheduler_config_maps_every_scheduler_setting() -> None:
    cfg = DffdConfig.model_validate(
        {
            "scheduler": {
                "burst_mode": "classic",
                "acquire_stable_frames": 7,
                "pan_tilt_mode": "absolute",
                "pan_tilt_feedforward": False,
                "pan_tilt_lost_s": 1.5,
                "pan_tilt_search_s": 0.5,
                "timing_margin_s": 0.002,
                "burst_policy": "sigma",
                "sigma_max_interval_frames": 40,
            }
        }
    )
    shared = scheduler_config(
        cfg, fps=25.0, exposure_s=0.004, focus_speed_counts_per_s=15000.0,
        focal_length_mm=4.0, pixel_pitch_mm=0.006, frame_size=(320, 240),
    )  # fmt: skip
    assert shared.burst_mode == "classic"
    assert shared.acquire_stable_frames == 7
    assert shared.pan_tilt_mode == "absolute"
    assert not shared.pan_tilt_feedforward
    assert (shared.pan_tilt_lost_s, shared.pan_tilt_search_s) == (1.5, 0.5)
    assert shared.timing_margin_s == 0.002
    assert shared.burst_every_frames == 40
    assert shared.baudrate == cfg.camera.baudrate


def test_pipeline_config_takes_the_service_estimator_settings() -> None:
    cfg = DffdConfig.model_validate(
        {
            "estimators": {
                "sigma_psi": 0.07,
                "sigma_beta": 0.02,
                "best": "kf",
                "focus_measure": "edge_variance",
            }
        }
    )
    pc = pipeline_config(cfg)
    assert (pc.cf2_sigma_psi, pc.cf2_sigma_beta, pc.best) == (0.07, 0.02, "kf")
    assert pc.focus_measure == "edge_variance"
    default = pipeline_config(DffdConfig())
    assert default.cf2_sigma_psi == DffdConfig().estimators.sigma_psi
    assert default.focus_measure == DffdConfig().estimators.focus_measure


def test_bench_pipeline_config_is_the_service_one_with_the_scenario_target() -> None:
    scenario = load_scenario("static")
    bench = bench_pipeline_config(scenario, DffdConfig())
    expected = dataclasses.replace(
        pipeline_config(DffdConfig()),
        known_size_m=scenario.target.known_size_m,
        settle_s=scenario.settle_s,
    )
    assert not scenario.estimator
    assert bench == expected


def test_scheduler_config_follows_the_scheduler_section() -> None:
    """sigma policy: bursts on σ growth (cadence only as a fallback); the other new keys pass."""
    from dffd.config import load_config
    from dffd.core.lens import Lens

    cfg = load_config(None)
    lens = Lens.from_toml(cfg.lens.file)
    facts = {
        "fps": 30.0, "exposure_s": 0.004, "focus_speed_counts_per_s": 20000.0,
        "focal_length_mm": lens.focal_length_mm, "pixel_pitch_mm": lens.pixel_pitch_mm,
        "frame_size": (640, 480),
    }  # fmt: skip
    every = scheduler_config(cfg, **facts)  # type: ignore[arg-type]
    assert (every.burst_every_frames, every.sigma_trigger_m) == (2, None)
    assert every.burst_mode == "rolling"
    assert (every.pan_tilt_mode, every.pan_tilt_feedforward, every.timing_margin_s) == (
        "drive", True, 0.003,
    )  # fmt: skip
    assert (every.acquire_stable_frames, every.pan_tilt_search_s) == (3, 2.0)
    cfg.scheduler.burst_policy = "sigma"
    cfg.scheduler.pan_tilt_mode = "absolute"
    sigma = scheduler_config(cfg, **facts)  # type: ignore[arg-type]
    assert (sigma.burst_every_frames, sigma.sigma_trigger_m) == (90, 0.05)
    assert sigma.pan_tilt_mode == "absolute"


def test_scheduler_speed_tables_come_from_the_camera_model_profile() -> None:
    for model, profile in (("evi-d100", EVI_D100), ("evi-d70", EVI_D70)):
        cfg = DffdConfig.model_validate({"camera": {"model": model}})
        sched = scheduler_config(
            cfg, fps=30.0, exposure_s=None, focus_speed_counts_per_s=20000.0,
            focal_length_mm=4.0, pixel_pitch_mm=0.006, frame_size=(640, 480),
        )  # fmt: skip
        assert sched.pan_speeds_deg_s == profile.pan_speeds_deg_s
        assert sched.tilt_speeds_deg_s == profile.tilt_speeds_deg_s
    # The two models' tables differ, so a scheduler on the D70 commands the D70's rates.
    assert EVI_D70.pan_speeds_deg_s != EVI_D100.pan_speeds_deg_s


def test_the_scheduler_counts_a_measured_stream_latency_in_frames() -> None:
    """[capture] latency_s (a stream's measured delay) sets the frames in flight the scheduler
    counts, at the camera's frame rate; unset, latency_frames does (it was always the latter)."""
    facts = {
        "exposure_s": None, "focus_speed_counts_per_s": 20000.0, "focal_length_mm": 4.0,
        "pixel_pitch_mm": 0.006, "frame_size": (640, 480),
    }  # fmt: skip
    default = DffdConfig()
    assert scheduler_config(default, fps=30.0, **facts).capture_latency_frames == 1  # type: ignore[arg-type]
    stream = DffdConfig.model_validate({"capture": {"latency_s": 0.16, "latency_frames": 1}})
    assert scheduler_config(stream, fps=30.0, **facts).capture_latency_frames == 5  # type: ignore[arg-type]
    assert scheduler_config(stream, fps=25.0, **facts).capture_latency_frames == 4  # type: ignore[arg-type]
    exact = DffdConfig.model_validate({"capture": {"latency_s": 0.1}})
    assert scheduler_config(exact, fps=30.0, **facts).capture_latency_frames == 3  # type: ignore[arg-type]
