"""Pydantic models of every MQTT payload (docs/design.md §7, §9), version ``"schema": 1``.

Conventions: ``t`` is UTC wall time (seconds since the epoch), ``t_mono`` the monotonic time in
seconds of the frame's exposure (or of the event), field names carry SI units (``z_m``,
``pan_deg``, ``rho_per_s``). Values must be finite (JSON has no NaN): an unknown value is
``null``. Build payloads through these models so the daemon can never publish something the
shipped JSON Schemas (``dffd/schemas/``) reject.
"""

from __future__ import annotations

import time
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

SCHEMA_VERSION: Final = 1

State = Literal["idle", "acquiring", "tracking", "lost"]
EstimatorName = Literal["lpv", "kf", "cf2", "cf1"]
Availability = Literal["online", "offline"]

NonNegInt = Annotated[int, Field(ge=0)]
NonNeg = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]
Meters = float
Vec3 = tuple[float, float, float]


_STRICT = ConfigDict(
    extra="forbid",
    frozen=True,
    allow_inf_nan=False,
    populate_by_name=True,
    # Published payloads always carry every key, so the shipped schemas mark every key required.
    json_schema_serialization_defaults_required=True,
)


def wall_time() -> float:
    """UTC wall-clock time in seconds since the epoch (the ``t`` field)."""
    return time.time()


class Payload(BaseModel):
    """Common base: frozen, strict about unknown keys, finite numbers only."""

    model_config = _STRICT

    schema_: Literal[1] = Field(
        default=SCHEMA_VERSION,
        validation_alias="schema",
        serialization_alias="schema",
        description="payload version",
    )

    def to_json(self) -> bytes:
        """The payload as compact UTF-8 JSON (``schema`` spelt without the underscore)."""
        return self.model_dump_json(by_alias=True).encode()


# -- estimate ----------------------------------------------------------------------------------


class DepthByEstimator(BaseModel):
    """Depth along the optical axis per estimator, metres; null where it has no value."""

    model_config = _STRICT

    measured: Meters | None = Field(description="depth-from-focus z_m if a burst completed now")
    cf1: Meters | None = Field(description="CF1 (known size); null without target.known_size_m")
    cf2: Meters | None = Field(description="CF2 (bias estimation); null before initialisation")
    lpv: Meters | None = Field(description="LPV observer; null before initialisation")
    kf: Meters | None = Field(description="time-varying Kalman filter; null before initialisation")


class SigmaByEstimator(BaseModel):
    """1σ of each estimator's depth, metres; null where it has no value."""

    model_config = _STRICT

    measured: NonNeg | None = Field(default=None, description="σ of z_m (the adapted fit σ)")
    cf1: NonNeg | None = Field(default=None, description="σ of CF1")
    cf2: NonNeg | None = Field(default=None, description="σ of CF2")
    lpv: NonNeg | None = Field(default=None, description="σ of the LPV observer")
    kf: NonNeg | None = Field(default=None, description="σ of the Kalman filter")


class Estimate(Payload):
    """``…/estimate``: one per frame with a contour."""

    seq: NonNegInt = Field(description="message counter, +1 per estimate since start")
    t: float = Field(description="UTC wall time, s since the epoch")
    t_mono: float = Field(description="monotonic time of the frame's exposure, s")
    state: State
    depth_m: DepthByEstimator
    best: EstimatorName = Field(description="which estimator z_m and sigma_m come from")
    z_m: Meters | None = Field(description="the best estimate of depth")
    sigma_m: Annotated[float, Field(ge=0)] | None = Field(description="1σ of z_m")
    sigmas_m: SigmaByEstimator | None = Field(
        default=None,
        description="1σ of every estimator's depth (adapted noise; docs/estimation.md §9)",
    )
    beta_m_s: float | None = Field(
        default=None, description="CF2's estimate of the size-rate bias β"
    )
    size_m: Annotated[float, Field(ge=0)] | None = Field(description="R̂, the target's real size")
    r_px: Annotated[float, Field(ge=0)] | None = Field(description="image size r = sqrt(tr Σ)")
    rho_per_s: float | None = Field(default=None, description="ρ = ṙ/r")
    position_m: Vec3 | None = Field(
        description="target position [x, y, z] in the world frame: the 3D tracker's when it holds"
        " a track, else the frame's back-projection (docs/tracking3d.md)"
    )
    velocity_m_s: Vec3 | None = Field(
        default=None,
        description="target velocity in the world frame: the 3D tracker's when it holds a track,"
        " else the smoothed derivative of the back-projected position",
    )
    acceleration_m_s2: Vec3 | None = Field(
        default=None, description="target acceleration in the world frame (3D tracker)"
    )
    angular_speed_rad_s: float | None = Field(
        default=None,
        description="turn rate of the velocity about the upward vertical, + counter-clockwise"
        " seen from above (3D tracker)",
    )
    position_sigma_m: tuple[NonNeg, NonNeg, NonNeg] | None = Field(
        default=None, description="1σ of position_m per world axis (3D tracker)"
    )
    model_probabilities: dict[str, Probability] | None = Field(
        default=None,
        description="the 3D tracker's motion-model probabilities (cv, ca, ct), summing to 1",
    )
    pan_deg: float
    tilt_deg: float
    focus_counts: NonNegInt | None = Field(
        default=None, description="focus setting during the exposure"
    )
    replayed: bool = Field(default=False, description="true when sent late from the outage backlog")


# -- measurement -------------------------------------------------------------------------------


class Fit(BaseModel):
    """The parabola g(v0) = α v0² + β v0 + γ fitted to one burst (docs/design.md §3)."""

    model_config = _STRICT

    alpha: float | None = Field(description="α, curvature of the cost parabola (must be > 0)")
    v_mm: float | None = Field(description="vertex v̂: lens-to-sensor distance where sharp, mm")
    residual: Annotated[float, Field(ge=0)] | None = Field(description="fit residual (RMS)")
    accepted: bool
    reason: str | None = Field(default=None, description="why the fit was rejected or flagged")


class Measurement(Payload):
    """``…/measurement``: one per three-focus burst."""

    seq: NonNegInt = Field(description="message counter, +1 per measurement since start")
    burst: NonNegInt = Field(description="burst id (as in FrameTag.burst)")
    t: float
    t_mono: float = Field(description="monotonic time of the burst's last exposure, s")
    focus_counts: Annotated[list[NonNegInt], Field(min_length=3)]
    v_mm: list[float] | None = Field(default=None, description="focus settings converted to v, mm")
    costs: Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=3)]
    fit: Fit
    z_m: Meters | None = Field(description="measured depth; null when the fit was rejected")
    sigma_m: Annotated[float, Field(ge=0)] | None = None
    replayed: bool = False

    @model_validator(mode="after")
    def _same_length(self) -> Measurement:
        n = len(self.focus_counts)
        if len(self.costs) != n or (self.v_mm is not None and len(self.v_mm) != n):
            msg = "focus_counts, costs and v_mm must have one entry per burst frame"
            raise ValueError(msg)
        return self


# -- status ------------------------------------------------------------------------------------


class Search(BaseModel):
    """The search sweep of automatic acquisition (pan/tilt visits its range view by view)."""

    model_config = _STRICT

    phase: Literal["waiting", "sweeping", "holding"] = Field(
        description="waiting: no target yet, a sweep starts at next_pass_in_s; sweeping: visiting "
        "views; holding: a sweep found nothing, the head waits where it began"
    )
    pass_number: NonNegInt = Field(description="sweeps so far since the target was last seen")
    view: NonNegInt = Field(description="views visited in this sweep")
    views: NonNegInt = Field(description="views in a sweep")
    elapsed_s: Annotated[float, Field(ge=0)] | None = Field(
        default=None, description="time since this (or the last) sweep began"
    )
    next_pass_in_s: Annotated[float, Field(ge=0)] | None = Field(
        default=None, description="waiting/holding: time until the next sweep"
    )


class Rates(BaseModel):
    """Achieved rates over the last status period, Hz."""

    model_config = _STRICT

    frame_hz: Annotated[float, Field(ge=0)]
    estimate_hz: Annotated[float, Field(ge=0)]
    depth_hz: Annotated[float, Field(ge=0)]
    depth_limit_hz: Annotated[float, Field(ge=0)] | None = Field(
        default=None, description="theoretical depth-measurement rate of this configuration"
    )


class LinkHealth(BaseModel):
    """Health of the VISCA serial link."""

    model_config = _STRICT

    connected: bool
    bytes_in: NonNegInt = 0
    bytes_out: NonNegInt = 0
    replies: NonNegInt = 0
    errors: NonNegInt = 0
    timeouts: NonNegInt = 0
    last_reply_age_s: Annotated[float, Field(ge=0)] | None = None
    reconnects: NonNegInt = 0
    ip_retransmits: NonNegInt | None = Field(
        default=None, description="VISCA over IP: datagrams resent after a late reply (else null)"
    )
    ip_given_up: NonNegInt | None = Field(
        default=None, description="VISCA over IP: datagrams abandoned after every retransmission"
    )
    ip_sequence_errors: NonNegInt | None = Field(
        default=None, description="VISCA over IP: sequence-number errors the camera reported"
    )
    ip_resets: NonNegInt | None = Field(
        default=None, description="VISCA over IP: RESETs of the sequence (connects included)"
    )


class VideoHealth(BaseModel):
    """Health of a network video stream (``[capture] source = "stream"`` or ``sim.video``)."""

    model_config = _STRICT

    url: str = Field(description="the stream, without its password")
    connected: bool
    frames: NonNegInt = 0
    reconnects: NonNegInt = Field(default=0, description="times the stream was lost and reopened")
    stream_timestamps: bool = Field(
        default=False,
        description="frame times from the stream's timestamps (false: arrival − latency_s)",
    )
    latency_s: Annotated[float, Field(ge=0)] = 0.0


class Drops(BaseModel):
    """Counters of data dropped by the bounded queues (all since start)."""

    model_config = _STRICT

    frames: NonNegInt = Field(default=0, description="frames dropped before the estimator thread")
    publish_queue: NonNegInt = Field(
        default=0, description="messages dropped from the publish queue"
    )
    backlog: NonNegInt = Field(default=0, description="messages dropped from the outage backlog")
    log: NonNegInt = Field(default=0, description="records dropped by the durable log")


class MqttHealth(BaseModel):
    """The MQTT client's own view (filled from ``Publisher.stats()``)."""

    model_config = _STRICT

    connected: bool
    reconnects: NonNegInt = 0
    published: NonNegInt = 0
    replayed: NonNegInt = 0
    backlog: NonNegInt = Field(default=0, description="messages waiting in the outage backlog now")


class Status(Payload):
    """``…/status`` (QoS 1, retained): availability, tracking state, rates and health."""

    availability: Availability = Field(description="'offline' is also the last will")
    t: float
    t_mono: float
    state: State | None = Field(default=None, description="null when offline")
    camera: str | None = None
    rates: Rates | None = None
    link: LinkHealth | None = None
    video: VideoHealth | None = Field(
        default=None, description="network video stream; null for a V4L2 device or the renderer"
    )
    mqtt: MqttHealth | None = None
    drops: Drops | None = None
    last_estimate_age_s: Annotated[float, Field(ge=0)] | None = Field(
        default=None,
        description="time since the last published estimate; null: none since start or release",
    )
    version: str
    message: str | None = Field(default=None, description="human-readable note, e.g. why offline")
    search: Search | None = Field(
        default=None,
        description="the search sweep while automatic acquisition has no target; null otherwise",
    )


# -- commands ----------------------------------------------------------------------------------

CommandId = Annotated[str, Field(max_length=128)] | int | None


class _CommandBase(BaseModel):
    model_config = _STRICT

    id: CommandId = Field(default=None, description="echoed in the reply")


class Acquire(_CommandBase):
    """Acquire the target inside ``roi`` [x, y, w, h] (pixels); without ``roi``, detect it."""

    cmd: Literal["acquire"]
    roi: (
        tuple[NonNegInt, NonNegInt, Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]] | None
    ) = Field(default=None, description="box to search, pixels; omitted or null: whole frame")


class Release(_CommandBase):
    """Stop tracking the current target."""

    cmd: Literal["release"]


class SetKnownSize(_CommandBase):
    """Set (or with null, forget) the target's real size; enables CF1."""

    cmd: Literal["set_known_size"]
    size_m: Annotated[float, Field(gt=0, le=10)] | None


class Home(_CommandBase):
    """Send pan/tilt home."""

    cmd: Literal["home"]


class SetBurstPolicy(_CommandBase):
    """Change when bursts are taken (same meaning and ranges as ``[scheduler]``)."""

    cmd: Literal["set_burst_policy"]
    policy: Literal["every_n", "sigma"]
    every_n_frames: Annotated[int, Field(ge=1, le=1000)] | None = None
    sigma_threshold_m: Annotated[float, Field(gt=0, le=10)] | None = None


class Ping(_CommandBase):
    """Liveness check; the reply carries the daemon's time."""

    cmd: Literal["ping"]


Command = Annotated[
    Acquire | Release | SetKnownSize | Home | SetBurstPolicy | Ping,
    Field(discriminator="cmd"),
]
COMMAND_ADAPTER: TypeAdapter[Command] = TypeAdapter(Command)
COMMAND_NAMES: tuple[str, ...] = (
    "acquire", "release", "set_known_size", "home", "set_burst_policy", "ping",
)  # fmt: skip


class CommandReply(Payload):
    """``…/cmd/reply``: the outcome of one command."""

    id: CommandId = Field(description="the command's id (null if it could not be read)")
    cmd: str | None = Field(default=None, description="the command name, if it could be read")
    ok: bool
    error: str | None = Field(
        default=None, description="what was wrong and what to do (when ok=false)"
    )
    result: dict[str, Any] | None = Field(default=None, description="command-specific data")
    t: float


# -- simulator truth ---------------------------------------------------------------------------


class Truth(Payload):
    """``…/sim/truth``: simulator ground truth per frame."""

    t: float | None = Field(default=None, description="UTC wall time, s")
    t_mono: float = Field(description="monotonic time of the frame's exposure, s")
    z_m: float = Field(description="true depth along the optical axis")
    position_m: Vec3 = Field(description="true target position [x, y, z] in the world frame")
    size_m: Annotated[float, Field(gt=0)] | None = None
    velocity_m_s: Vec3 | None = Field(
        default=None, description="true target velocity in the world frame"
    )
    acceleration_m_s2: Vec3 | None = Field(
        default=None, description="true target acceleration in the world frame"
    )
    angular_speed_rad_s: float | None = Field(
        default=None,
        description="true turn rate of the velocity about the upward vertical, + counter-clockwise"
        " seen from above (docs/tracking3d.md)",
    )
    in_view: bool | None = Field(
        default=None, description="the target's whole outline lies inside the frame"
    )


def parse_command(payload: bytes | str) -> Command:
    """Validate a command payload (raises pydantic.ValidationError or ValueError)."""
    return COMMAND_ADAPTER.validate_json(payload)
