"""Typed scenario files (``hil/scenarios/*.toml``): what the bench runs and how it scores it.

A scenario names a target, a trajectory, the simulated camera's parameters, the seeds, and the
baselines to run. Coordinates are the camera frame at pan = tilt = 0 (OpenCV convention: x right,
y down, z forward, metres); the camera's pan/tilt head sits at the origin. A scenario may hold
several *cases* (e.g. static targets at several depths): each case overrides trajectory keys and
runs as its own session (fresh simulator and estimator), and the report pools them.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.sim.config import OpticsModelName, SimConfigError
from drivers.sim.resources import world_tables

SCENARIO_DIR = Path(__file__).parent / "scenarios"
OPTICS_MODELS: tuple[str, ...] = get_args(OpticsModelName)
SCENARIO_NAMES = (
    "static",
    "approach",
    "paper-circle",
    "figure-eight",
    "random",
    "line",
    "stop-and-go",
)


class ScenarioError(ValueError):
    """A scenario is missing, not valid TOML, or violates the schema; the message says which."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TargetSpec(_Model):
    """The planar target the simulator renders."""

    shape: Literal["disc", "polygon", "textured", "aruco"] = "disc"
    size_m: float = Field(0.03576, gt=0.0, le=2.0)  # R = sqrt(tr Σ) of the boundary
    # Given to CF1 and the known-size baseline only; the unknown-size estimators never see it.
    known_size_m: float | None = Field(None, gt=0.0)
    rotation_dps: float = 0.0  # spin about the optical axis, degrees per second


class TrajectorySpec(_Model):
    """A target trajectory; which keys matter depends on ``kind``."""

    kind: Literal["static", "linear", "stop-and-go", "circle", "figure-eight", "random"]
    position_m: tuple[float, float, float] = (0.0, 0.0, 5.0)  # static; start of linear/stop-and-go
    end_m: tuple[float, float, float] = (0.0, 0.0, 2.0)  # linear: end (then at rest); stop-and-go
    center_m: tuple[float, float, float] = (0.0, 0.0, 6.0)  # circle / figure-eight / random
    radius_m: float = Field(4.0, gt=0.0)  # circle radius; figure-eight half-extent
    speed_mps: float = Field(0.25, ge=0.0, le=5.0)  # path speed (random: mean speed)
    phase_deg: float = 0.0  # circle / figure-eight start phase
    extent_m: tuple[float, float, float] = (2.0, 0.3, 3.0)  # random: half-box around center
    stop_s: float = Field(3.0, ge=0.0, le=600.0)  # stop-and-go: rest at each end


class CameraSpec(_Model):
    """Simulated-camera parameters the scenario sets on top of the simulator's camera config.

    Unset (None) keeps the camera config's value.
    """

    # The simulated camera's TOML; None: the reference camera (drivers/sim/data/sim-camera.toml).
    config: str | None = None
    # What the estimator is told: a packaged lens table's name (dffd/defaults/lenses/) or a path.
    lens: str = "sim-evi-d100"
    fps: float | None = Field(None, gt=0.0, le=120.0)
    read_noise_dn: float | None = Field(None, ge=0.0)
    capture_latency_frames: float | None = Field(None, ge=0.0, le=10.0)
    focus_jitter_counts: float | None = Field(None, ge=0.0)
    motion_blur: bool | None = None
    # The simulator's optics model (``[optics] model``: reference | aberrated). With a model other
    # than the reference one the estimator is told that model's own ground-truth lens table
    # instead of ``lens`` (hil/simbuild.py).
    optics: OpticsModelName | None = None
    # Extra dotted keys handed to the simulator's config (names as in drivers/sim/config.py),
    # e.g. ``"lens.residual_blur_px" = 0.8``.
    overrides: dict[str, Any] = Field(default_factory=dict)


class BaselineSpec(_Model):
    """Which baselines run, and how."""

    known_size: bool = True
    aruco: bool = True
    full_sweep: bool = True
    # Classic depth from focus: settings spread evenly over the focus range in each sweep.
    full_sweep_settings: int = Field(16, ge=5, le=64)
    # Krotkov-style coarse-to-fine sweep (same sharpness measure as the full sweep): a coarse
    # pass over the whole range, then a fine pass over ± one coarse step around its peak.
    coarse_fine: bool = True
    coarse_settings: int = Field(8, ge=4, le=64)
    fine_settings: int = Field(7, ge=3, le=64)
    # The ArUco and full-sweep passes need their own frames; cap their length to keep runs short.
    max_pass_s: float = Field(60.0, gt=0.0)


class ThresholdSpec(_Model):
    """Goals checked in the report (docs/design.md §10, issue 6)."""

    ss_std_max_m: float | None = None  # best estimator's steady-state std must be below this
    ss_std_vs_measured_max: float | None = None  # … and at most this fraction of raw z_m's
    sweep_rate_ratio_min: float | None = None  # depth_hz / full_sweep_depth_hz at least this


class CaseSpec(_Model):
    """One session of a multi-case scenario: a name and trajectory keys to override."""

    name: str
    trajectory: dict[str, Any] = Field(default_factory=dict)


class Scenario(_Model):
    """A validated scenario file."""

    name: str
    # The simulator's world (drivers/sim/data/worlds/<world>.toml) that [target] and [trajectory]
    # start from; the scenario's own tables override its keys. Resolved by load_scenario.
    world: str | None = None
    description: str = ""
    duration_s: float = Field(gt=0.0, le=3600.0)  # per case
    settle_s: float = Field(5.0, ge=0.0)  # steady state starts this long after the start
    seeds: tuple[int, ...] = (1,)
    target: TargetSpec = Field(default_factory=lambda: TargetSpec.model_validate({}))
    trajectory: TrajectorySpec
    camera: CameraSpec = Field(default_factory=lambda: CameraSpec.model_validate({}))
    baselines: BaselineSpec = Field(default_factory=lambda: BaselineSpec.model_validate({}))
    thresholds: ThresholdSpec = Field(default_factory=lambda: ThresholdSpec.model_validate({}))
    cases: tuple[CaseSpec, ...] = ()
    # Overrides of dffd.scheduler.SchedulerConfig / dffd.core.pipeline_config.PipelineConfig
    # fields for experiments (default: none — the bench measures the product's defaults).
    scheduler: dict[str, Any] = Field(default_factory=dict)
    estimator: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check(self) -> Scenario:
        if not self.seeds:
            raise ValueError("seeds must list at least one seed")
        if self.settle_s >= self.duration_s:
            raise ValueError(f"settle_s ({self.settle_s}) must be below duration_s")
        for case in self.cases:
            self.trajectory.model_copy(update=case.trajectory)  # keys checked in expand()
        return self

    def expand(self) -> list[tuple[str, TrajectorySpec]]:
        """The sessions to run: ``[(case name, trajectory)]`` (one unnamed case if none given)."""
        if not self.cases:
            return [(self.name, self.trajectory)]
        out = []
        for case in self.cases:
            merged = self.trajectory.model_dump() | case.trajectory
            try:
                out.append((case.name, TrajectorySpec.model_validate(merged)))
            except ValidationError as exc:
                raise ScenarioError(f"scenario {self.name} case {case.name}: {exc}") from exc
        return out

    def with_settings(self, assignments: list[str]) -> Scenario:
        """A copy with ``section.key=value`` assignments (value parsed as TOML, else a string).

        Sections: ``scheduler``, ``estimator``, ``camera`` (simulator dotted keys go through
        ``camera.overrides``: ``camera.lens.residual_blur_px=0.8``).
        """
        sched, est, cam = dict(self.scheduler), dict(self.estimator), dict(self.camera.overrides)
        for item in assignments:
            key, sep, raw = item.partition("=")
            section, dot, name = key.partition(".")
            if not sep or not dot or section not in ("scheduler", "estimator", "camera"):
                raise ScenarioError(
                    f"--set {item!r}: expected scheduler.KEY=VALUE, estimator.KEY=VALUE or "
                    "camera.SECTION.KEY=VALUE"
                )
            try:
                value: Any = tomllib.loads(f"v = {raw}")["v"]
            except tomllib.TOMLDecodeError:
                value = raw
            {"scheduler": sched, "estimator": est, "camera": cam}[section][name] = value
        camera = self.camera.model_copy(update={"overrides": cam})
        return self.model_copy(update={"scheduler": sched, "estimator": est, "camera": camera})

    def with_optics(self, model: OpticsModelName) -> Scenario:
        """A copy rendered by the simulator's optics ``model`` (``python -m hil run --optics``)."""
        return self.model_copy(update={"camera": self.camera.model_copy(update={"optics": model})})

    def shortened(self, duration_s: float) -> Scenario:
        """A copy running ``duration_s`` per case (settling scaled down to fit), for smoke tests."""
        settle = min(self.settle_s, 0.5 * duration_s)
        return self.model_copy(update={"duration_s": duration_s, "settle_s": settle})


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by name (``hil/scenarios/NAME.toml``) or by path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = SCENARIO_DIR / f"{name_or_path}.toml"
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        known = ", ".join(available_scenarios())
        raise ScenarioError(
            f"no scenario {name_or_path!r} (looked for {path}); known scenarios: {known}"
        ) from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"scenario file {path} is not valid TOML: {exc}") from exc
    except OSError as exc:
        raise ScenarioError(f"cannot read scenario file {path}: {exc.strerror}") from exc
    if isinstance(data.get("world"), str):
        try:
            world = world_tables(data["world"])
        except SimConfigError as exc:
            raise ScenarioError(f"scenario file {path}: world: {exc}") from exc
        for table in ("target", "trajectory"):
            own = data.get(table, {})
            data[table] = world[table] | own if isinstance(own, dict) else own
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(f"scenario file {path} is invalid: {exc}") from exc


def available_scenarios() -> list[str]:
    """Names of the scenario files shipped in ``hil/scenarios``."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
