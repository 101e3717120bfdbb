"""Build the simulated camera of a scenario session on a virtual clock (lock-step mode).

Everything physical comes from ``drivers/sim`` (config, world, optics, frame source, VISCA
device); the scenario only selects parameters. The estimator's lens table is the file the
scenario names; when it is missing (the simulator's calibration not yet written) the bench writes
the simulator's ground-truth table to a temporary file and says so in the run's notes.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dffd.resources import ResourceNotFoundError, is_lens_name, lens_table
from drivers.frames import Frame
from drivers.sim.config import (
    SimCameraConfig,
    load_sim_camera_config,
    with_overrides,
)
from drivers.sim.device_types import DeviceConfig
from drivers.sim.optics import Optics
from drivers.sim.resources import reference_camera_file
from drivers.sim.rig import SimCamera, build_sim_camera
from drivers.sim.source import FrameTruth, SimFrameSource
from drivers.sim.state import CameraState
from drivers.sim.world import World
from hil.scenario import Scenario, TrajectorySpec

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
# Virtual time of the first exposure's middle: the device is up and the first focus move lands.
T_FIRST_FRAME_S = 0.5


@dataclass
class SimSession:
    """One simulated camera + world in virtual time, and the estimator's lens table."""

    rig: SimCamera
    lens_path: Path
    notes: list[str] = field(default_factory=list)

    @property
    def config(self) -> SimCameraConfig:
        """The simulated camera's configuration."""
        return self.rig.config

    @property
    def state(self) -> CameraState:
        """The camera's mechanical state (on the virtual clock)."""
        return self.rig.state

    @property
    def source(self) -> SimFrameSource:
        """The renderer."""
        return self.rig.source

    @property
    def world(self) -> World:
        """The target and its trajectory."""
        return self.rig.world

    @property
    def device_config(self) -> DeviceConfig:
        """How the VISCA device model behaves."""
        return self.rig.device_config

    @property
    def fps(self) -> float:
        """Frame rate."""
        return self.config.capture.fps

    @property
    def exposure_s(self) -> float:
        """Exposure duration."""
        return self.config.capture.exposure_s

    @property
    def latency_frames(self) -> float:
        """Frame periods between the end of an exposure and delivery."""
        return self.config.capture.capture_latency_frames

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.source.frame_size

    def set_time(self, t: float) -> None:
        """Advance the virtual clock (never backwards)."""
        self.rig.virtual_clock.set(t)

    def frame_time(self, index: int) -> float:
        """Mid-exposure time of frame ``index``."""
        return self.source.frame_time(index)

    def delivery_time(self, index: int) -> float:
        """When frame ``index`` is delivered."""
        return self.source.delivery_time(index)

    def render(self, index: int) -> tuple[Frame, FrameTruth]:
        """Render frame ``index`` and its ground truth."""
        frame = self.source.render_frame(index)
        truth = self.source.truth_for(index)
        assert truth is not None
        return frame, truth


def sim_camera_config(
    scenario: Scenario, trajectory: TrajectorySpec, seed: int, target_shape: str | None = None
) -> tuple[SimCameraConfig, list[str]]:
    """The simulated-camera config of a session: camera file + scenario parameters + world."""
    notes: list[str] = []
    if scenario.camera.config is None:
        base = load_sim_camera_config(reference_camera_file())
    else:
        path = _resolve(scenario.camera.config)
        if path.exists():
            base = load_sim_camera_config(path)
        else:
            base = SimCameraConfig()
            notes.append(f"{scenario.camera.config} missing: simulator defaults used")
    cam = scenario.camera
    overrides: dict[str, Any] = {"seed": seed}
    if cam.fps is not None:
        overrides["capture.fps"] = cam.fps
    if cam.read_noise_dn is not None:
        overrides["sensor.read_noise_dn"] = cam.read_noise_dn
    if cam.capture_latency_frames is not None:
        overrides["capture.capture_latency_frames"] = cam.capture_latency_frames
    if cam.focus_jitter_counts is not None:
        overrides["lens.focus_jitter_counts"] = cam.focus_jitter_counts
    if cam.motion_blur is not None:
        overrides["capture.motion_blur"] = cam.motion_blur
    if cam.optics is not None:
        overrides["optics.model"] = cam.optics
    overrides.update(cam.overrides)
    target = scenario.target.model_dump()
    if target_shape is not None:
        target["shape"] = target_shape
    traj = trajectory.model_dump() | {"seed": seed}
    overrides["world.target"] = target
    overrides["world.trajectory"] = traj
    return with_overrides(base, overrides), notes


def build_session(
    scenario: Scenario,
    trajectory: TrajectorySpec,
    seed: int,
    *,
    target_shape: str | None = None,
    lens_path: Path | None = None,
) -> SimSession:
    """A ready simulated camera for one session, its virtual clock at 0; the estimator is told
    ``lens_path`` when given (a calibrated table, hil/calibration.py)."""
    config, notes = sim_camera_config(scenario, trajectory, seed, target_shape)
    # The bench starts the camera powered up in manual focus (the daemon's initialisation is
    # not what it measures).
    device = DeviceConfig(pace=True, autofocus_at_power_up=False, network_change_at_power_up=False)
    rig = build_sim_camera(config, device=device, virtual_start_s=0.0, t0=T_FIRST_FRAME_S)
    if lens_path is not None:
        return SimSession(rig, lens_path, notes)
    if config.optics.model != "reference":
        # The packaged tables describe the reference lens: another optics model's estimator is
        # told that model's ground truth (a table `dffd calibrate --sim` fits is issue 11.7).
        lens_path = truth_lens_table(config)
        notes.append(f"optics {config.optics.model}: the simulator's ground-truth lens table used")
        return SimSession(rig, lens_path, notes)
    lens_path = lens_file(scenario.camera.lens)
    if not lens_path.exists():
        lens_path = truth_lens_table(config)
        notes.append(f"{scenario.camera.lens} missing: the simulator's ground-truth table was used")
    return SimSession(rig, lens_path, notes)


def optics_model(scenario: Scenario) -> str:
    """The simulator optics model the scenario's sessions render with."""
    _, trajectory = scenario.expand()[0]
    config, _ = sim_camera_config(scenario, trajectory, scenario.seeds[0])
    return config.optics.model


def lens_file(name_or_path: str) -> Path:
    """A scenario's lens: a packaged table's name (dffd/defaults/lenses/) or a path."""
    if is_lens_name(name_or_path):
        try:
            return lens_table(name_or_path)
        except ResourceNotFoundError:
            return Path(name_or_path)  # reported as missing by the caller
    return _resolve(name_or_path)


def _resolve(path: str) -> Path:
    p = Path(path)
    return p if p.is_absolute() else REPO_ROOT / p


_LENS_CACHE: dict[int, Path] = {}


def truth_lens_table(config: SimCameraConfig) -> Path:
    """The simulator's ground-truth lens table of ``config`` (a temporary file, memoised)."""
    key = hash((config.lens.model_dump_json(), config.optics.model_dump_json(), config.zoom_counts))
    if key not in _LENS_CACHE:
        handle = tempfile.NamedTemporaryFile(  # noqa: SIM115 - kept for the process lifetime
            "w", suffix=".toml", prefix="hil-lens-", delete=False
        )
        handle.close()
        Optics.from_config(config).write_lens_table(handle.name, config.zoom_counts)
        _LENS_CACHE[key] = Path(handle.name)
    return _LENS_CACHE[key]


def image_of(frame: Frame) -> npt.NDArray[np.uint8]:
    """The frame's pixels."""
    return frame.image
