"""Typed configuration of the simulated camera and its world, loaded from TOML.

``drivers/sim/data/sim-camera.toml`` is the reference camera (package data, see
:mod:`drivers.sim.resources`); every value there carries its source or the
assumption behind it. Units are in the field names (``_mm``, ``_m``, ``_px``, ``_dn`` = digital
numbers of the 8-bit output, ``_s``). Coordinates follow docs/design.md §11: the world
frame is the camera frame at pan = tilt = 0 (OpenCV: x right, y down, z forward, metres) with
the pan/tilt head at the origin; "horizontal" is the x–z plane.

Trajectory and target keys match ``hil/scenario.py`` (``TrajectorySpec``, ``TargetSpec``) so a
scenario's blocks validate here unchanged.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

Vec3 = tuple[float, float, float]


class SimConfigError(ValueError):
    """A simulated-camera config file is missing, not TOML, or invalid; the message says which."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorConfig(_Model):
    """Image sensor: geometry and the photometric noise model."""

    width_px: int = Field(default=640, ge=16, le=8192)
    height_px: int = Field(default=480, ge=16, le=8192)
    pixel_pitch_mm: float = Field(default=0.005, gt=0.0, le=0.1)
    # Conversion gain; shot-noise variance in DN² is signal_DN / gain. 0 turns shot noise off.
    gain_e_per_dn: float = Field(default=40.0, ge=0.0)
    read_noise_dn: float = Field(default=2.0, ge=0.0, le=50.0)


class LensConfig(_Model):
    """The zoom lens: focal length and f-number against zoom counts, and the focus mechanics."""

    name: str = "sim-evi-d100"
    # [zoom counts, focal length mm], counts strictly increasing, focal length strictly increasing.
    zoom_table: tuple[tuple[int, float], ...] = ((0x0000, 3.1), (0x4000, 31.0))
    # [zoom counts, f-number at full aperture]; interpolated linearly in focal length.
    f_number_table: tuple[tuple[int, float], ...] = ((0x0000, 1.8), (0x4000, 2.9))
    focus_far_counts: int = Field(default=0x1000, ge=0, le=0xFFFF)  # focused at infinity
    focus_near_counts: int = Field(default=0x8400, ge=0, le=0xFFFF)  # focused at near_focus_m
    near_focus_m: float = Field(default=0.8, gt=0.0)
    # counts → object-side focus power P: P = P_near · u (1 + a u) / (1 + a), u ∈ [0, 1] the
    # normalised counts; a > 0 gives finer steps (more counts per dioptre) towards infinity.
    focus_curvature: float = Field(default=0.8, ge=0.0, le=10.0)
    residual_blur_px: float = Field(default=0.6, ge=0.0, le=10.0)  # Gaussian σ0 of the focused PSF
    psf: Literal["disc", "gaussian"] = "disc"
    # Magnification v0/z (thin lens, chief ray) instead of the pinhole f/z of docs/design.md §3.4.
    breathing: bool = False
    # σ of the focus motor's landing error per move, in counts (repeatability).
    focus_jitter_counts: float = Field(default=0.0, ge=0.0, le=1000.0)

    @model_validator(mode="after")
    def _check(self) -> LensConfig:
        tables = (("zoom_table", self.zoom_table), ("f_number_table", self.f_number_table))
        for name, table in tables:
            if len(table) < 2:
                raise ValueError(f"{name} needs at least two [counts, value] rows")
            counts = [c for c, _ in table]
            if any(b <= a for a, b in itertools.pairwise(counts)):
                raise ValueError(f"{name} counts must be strictly increasing")
            if any(value <= 0.0 for _, value in table):
                raise ValueError(f"{name} values must be positive")
        focal = [f for _, f in self.zoom_table]
        if any(b <= a for a, b in itertools.pairwise(focal)):
            raise ValueError("zoom_table focal lengths must increase with zoom counts")
        if self.focus_near_counts <= self.focus_far_counts:
            raise ValueError("focus_near_counts must be above focus_far_counts")
        return self


# The optics models the simulator renders with (drivers/sim/optics.py, optics_aberrated.py).
OpticsModelName = Literal["reference", "aberrated"]


class OpticsModelConfig(_Model):
    """Which optics model renders the frames, and the parameters of the aberrated one.

    ``reference``: the lens of ``drivers/sim/optics.py`` (uniform blur disc, focus power
    quadratic in counts, uniform background). ``aberrated``: ``drivers/sim/optics_aberrated.py``
    (ray-traced defocus with balanced spherical aberration, another focus cam, a textured
    background wall, signal-dependent noise) — a lens the estimator was not tuned on.
    """

    model: OpticsModelName = "reference"
    # Transverse spherical aberration at the rim of the pupil, px (balanced against defocus so
    # that the smallest RMS spot is at the nominal focus). Assumption: a fast zoom at full
    # aperture, a caustic ring of ~2 px on one side of focus.
    spherical_px: float = Field(default=2.5, ge=0.0, le=20.0)
    # Gaussian σ of diffraction + sensor cell + analog chain on top of the ray PSF, px.
    residual_blur_px: float = Field(default=0.5, ge=0.0, le=10.0)
    # Focus cam: P = P_near · [(e^{κu} − 1)/(e^κ − 1) + ε sin(2π m u)/(2π m)], u ∈ [0, 1].
    focus_exponent: float = Field(default=1.6, ge=0.0, le=6.0)  # κ
    focus_ripple: float = Field(default=0.12, ge=0.0, le=0.3)  # ε (monotone while ε < κ/(e^κ−1))
    focus_ripple_cycles: int = Field(default=2, ge=1, le=8)  # m
    near_focus_m: float = Field(default=0.9, gt=0.0)
    lens_name: str = "sim-aberrated"
    # A textured wall behind the target (band-limited noise), DN peak-to-mean, at this depth.
    background_contrast_dn: float = Field(default=12.0, ge=0.0, le=100.0)
    background_depth_m: float = Field(default=25.0, gt=0.0)
    background_seed: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> OpticsModelConfig:
        kappa = self.focus_exponent
        slope0 = 1.0 if kappa == 0.0 else kappa / math.expm1(kappa)  # cam slope at infinity
        if self.focus_ripple >= slope0:
            raise ValueError(
                f"optics.focus_ripple {self.focus_ripple} must stay below {slope0:.3f} "
                "(the cam slope at infinity) or the focus curve is not monotone"
            )
        return self


class CaptureConfig(_Model):
    """Frame timing of the simulated capture path."""

    fps: float = Field(default=30.0, gt=0.0, le=240.0)
    exposure_s: float = Field(default=0.004, gt=0.0, le=1.0)
    # Frame periods from mid-exposure to delivery (frames in flight), on top of exposure/2.
    capture_latency_frames: float = Field(default=1.0, ge=0.0, le=10.0)
    motion_blur: bool = True
    queue_frames: int = Field(default=4, ge=1, le=64)  # delivered frames held for next_frame()
    truth_frames: int = Field(default=1024, ge=16, le=1_000_000)  # truth kept for truth_for()

    @model_validator(mode="after")
    def _check(self) -> CaptureConfig:
        if self.exposure_s > 1.0 / self.fps:
            raise ValueError(f"exposure_s {self.exposure_s} exceeds the frame period 1/fps")
        return self


class TargetConfig(_Model):
    """The planar target (keys as ``hil.scenario.TargetSpec``)."""

    # irregular: a smooth non-convex outline from texture_seed (drivers/sim/outline.py)
    shape: Literal["disc", "polygon", "textured", "aruco", "irregular"] = "disc"
    size_m: float = Field(default=0.03576, gt=0.0, le=2.0)  # R = sqrt(tr Σ) of the boundary
    known_size_m: float | None = None  # accepted (scenario files carry it); unused here
    rotation_dps: float = 0.0  # spin about the line of sight
    roll_deg: float = 0.0  # initial rotation about the line of sight
    sides: int = Field(default=6, ge=3, le=64)  # polygon
    foreground_dn: float = Field(default=200.0, ge=0.0, le=255.0)  # disc/polygon face; card white
    dark_dn: float = Field(default=12.0, ge=0.0, le=255.0)  # ArUco black; texture dark level
    texture_seed: int = Field(default=0, ge=0)
    aruco_dictionary: str = "DICT_4X4_50"
    aruco_id: int = Field(default=0, ge=0)


class TrajectoryConfig(_Model):
    """A target trajectory (keys as ``hil.scenario.TrajectorySpec``); see drivers/sim/world.py."""

    kind: Literal["static", "linear", "stop-and-go", "circle", "figure-eight", "random"] = "static"
    position_m: Vec3 = (0.0, 0.0, 5.0)  # static; start of linear / stop-and-go
    end_m: Vec3 = (0.0, 0.0, 2.0)  # linear: end point (then it stops); stop-and-go: other end
    center_m: Vec3 = (0.0, 0.0, 6.0)  # circle / figure-eight / random
    radius_m: float = Field(default=4.0, gt=0.0)  # circle radius; figure-eight half-extent
    speed_mps: float = Field(default=0.25, ge=0.0, le=5.0)  # path speed (random: mean speed)
    phase_deg: float = 0.0  # circle / figure-eight start phase
    extent_m: Vec3 = (2.0, 0.3, 3.0)  # random: half-box around center
    seed: int = Field(default=0, ge=0)  # random
    stop_s: float = Field(default=3.0, ge=0.0, le=600.0)  # stop-and-go: rest at each end


class WorldConfig(_Model):
    """What the camera looks at."""

    background_dn: float = Field(default=40.0, ge=0.0, le=255.0)
    target: TargetConfig = TargetConfig()
    trajectory: TrajectoryConfig = TrajectoryConfig()


class SimCameraConfig(_Model):
    """The whole simulated camera (``drivers/sim/data/sim-camera.toml``)."""

    sensor: SensorConfig = SensorConfig()
    lens: LensConfig = LensConfig()
    capture: CaptureConfig = CaptureConfig()
    optics: OpticsModelConfig = OpticsModelConfig()
    zoom_counts: int = Field(default=0x4000, ge=0, le=0x4000)  # fixed zoom the camera starts at
    seed: int = Field(default=0, ge=0)  # noise and focus-jitter stream
    world: WorldConfig = WorldConfig()


def load_sim_camera_config(path: str | Path) -> SimCameraConfig:
    """Load and validate a simulated-camera TOML file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SimConfigError(f"cannot read simulated-camera config {path}: {exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SimConfigError(f"{path} is not valid TOML: {exc}") from exc
    try:
        return SimCameraConfig.model_validate(data)
    except ValidationError as exc:
        raise SimConfigError(f"{path} is not a valid simulated-camera config: {exc}") from exc


def with_overrides(config: SimCameraConfig, overrides: Mapping[str, Any]) -> SimCameraConfig:
    """A copy with dotted keys (``"lens.residual_blur_px"``) or nested tables replaced."""
    data = config.model_dump()
    for key, value in overrides.items():
        node = data
        *parents, leaf = key.split(".")
        for part in parents:
            child = node.get(part)
            if not isinstance(child, dict):
                raise SimConfigError(f"override {key!r}: {part!r} is not a config section")
            node = child
        if isinstance(value, Mapping) and isinstance(node.get(leaf), dict):
            node[leaf] = {**node[leaf], **value}
        else:
            node[leaf] = value
    try:
        return SimCameraConfig.model_validate(data)
    except ValidationError as exc:
        raise SimConfigError(
            f"invalid simulated-camera overrides {dict(overrides)}: {exc}"
        ) from exc
