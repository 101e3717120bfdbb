"""The configuration's pydantic models: one section per TOML table, ``DffdConfig`` the whole.

Every field has a default and a range; unknown keys are errors. Sections are named ``…Section``
(``SchedulerSection``) so they never share a name with the dataclasses the core and the scheduler
are configured with (``dffd.scheduler.SchedulerConfig``); ``dffd.wiring`` turns one into the other.
Cross-field rules are validators here, so ``dffd check-config`` and ``dffd run`` refuse the same
files. Build a ``DffdConfig`` with :func:`dffd.config.load_config`.

Kept whole (~640 lines): one schema, its tables in the order of ``dffd.toml``, read as the
reference of every key; the length is the keys' ranges and descriptions. Split per table, the ten
sections (15-115 lines each) would need their shared base and error helpers made public, and the
cross-section rules of ``DffdConfig`` would sit apart from the fields they check.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_core import PydanticCustomError
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from dffd.config.explain import ENV_NESTED_DELIMITER, ENV_PREFIX, ConfigError, show_value
from dffd.literals import BestEstimator, BurstMode, BurstPolicy, FocusMeasure, PanTiltMode
from dffd.resources import DEFAULT_LENS, ResourceNotFoundError, is_lens_name, lens_table
from dffd.web.listen import WebConfigError, is_loopback, parse_listen
from drivers.sim.resources import world_file, world_names
from drivers.visca.url import parse_camera_url

__all__ = [
    "DEFAULT_MQTTS_PORT",
    "DEFAULT_MQTT_PORT",
    "EMBEDDED_HOST",
    "ENV_NESTED_DELIMITER",
    "ENV_PREFIX",
    "CameraSection",
    "CaptureSection",
    "DffdConfig",
    "EstimatorsSection",
    "LensSection",
    "LogLevel",
    "LogSection",
    "MqttEndpoint",
    "MqttSection",
    "SchedulerSection",
    "SimSection",
    "TargetSection",
    "WebSection",
]


_CAMERA_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_TOPIC_PREFIX_RE = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")
_MQTT_URL_RE = re.compile(
    r"(?P<scheme>mqtts?)://(?P<host>\[[0-9A-Fa-f:.]+\]|[^:/\s\[\]@]+)(:(?P<port>\d{1,5}))?/?"
)
_FOURCC_RE = re.compile(r"[ -~]{4}")
DEFAULT_MQTT_PORT = 1883  # IANA port for MQTT
DEFAULT_MQTTS_PORT = 8883  # IANA port for MQTT over TLS
EMBEDDED_HOST = "127.0.0.1"  # the embedded broker never listens beyond loopback

LogLevel = Literal["DEBUG", "INFO", "WARNING", "ERROR"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True, allow_inf_nan=False)


def _field_error(field: str, message: str) -> PydanticCustomError:
    """A cross-field error reported at ``<section>.<field>`` rather than at the section."""
    return PydanticCustomError("dffd_field", "{message}", {"field": field, "message": message})


def _value_error(message: str) -> PydanticCustomError:
    return PydanticCustomError("dffd", "{message}", {"message": message})


class CameraSection(_Section):
    """``[camera]``: which camera and how to reach it."""

    name: str = Field(default="sim", description="camera name, used in topics dffd/<name>/…")
    driver: Literal["sim", "visca"] = Field(default="sim", description="sim = simulated camera")
    port: str | None = Field(
        default=None,
        description="where a VISCA camera is: a serial port (/dev/visca0) or other pyserial URL "
        "(socket://host:4001), raw VISCA over TCP (tcp://host:5678) or VISCA over IP "
        "(visca-ip://host:52381)",
    )
    baudrate: Literal[9600, 38400] = 9600
    address: Annotated[int, Field(ge=1, le=7)] = 1
    model: Literal["evi-d100", "evi-d70", "srg-300"] = Field(
        default="evi-d100",
        description="camera model (its limits and speed tables); the camera's version inquiry "
        "is checked against it at start-up",
    )

    @field_validator("name")
    @classmethod
    def _name_is_topic_safe(cls, value: str) -> str:
        if not _CAMERA_NAME_RE.fullmatch(value):
            raise _value_error(
                f"{value!r} is not a usable camera name; use 1–64 letters, digits, '_', '-' or '.'"
                " (it becomes an MQTT topic level)"
            )
        return value

    @field_validator("port")
    @classmethod
    def _port_is_a_camera_url(cls, value: str | None) -> str | None:
        """The driver's own parser: a port check-config passes is one the link can open."""
        if value:  # unset or empty: _visca_needs_port says whether one is required
            try:
                parse_camera_url(value)
            except ValueError as exc:
                raise _value_error(str(exc)) from None
        return value

    @model_validator(mode="after")
    def _visca_needs_port(self) -> CameraSection:
        if self.driver == "visca" and not self.port:
            raise _field_error(
                "port", "required when camera.driver is 'visca' (e.g. /dev/visca0 or /dev/ttyUSB0)"
            )
        return self


class CaptureSection(_Section):
    """``[capture]``: the frame source."""

    source: Literal["sim", "v4l2", "stream"] = Field(
        default="sim",
        description="sim = the simulated camera's renderer, v4l2 = a video device (device), "
        "stream = network video or a video file through FFmpeg (url)",
    )
    device: str | Annotated[int, Field(ge=0)] | None = Field(
        default=None, description="v4l2 device path (/dev/video0) or index"
    )
    url: str | None = Field(
        default=None,
        description="source = 'stream': rtsp://…, http://… (MJPEG) or the path of a video file",
    )
    latency_s: Annotated[float, Field(ge=0, le=5)] | None = Field(
        default=None,
        description="mid-exposure → delivery delay in seconds (measured by dffd calibrate "
        "--latency); unset: latency_frames / fps",
    )
    timestamps: Literal["auto", "stream", "arrival"] = Field(
        default="auto",
        description="source = 'stream': frame times from the stream's timestamps (stream), from "
        "arrival − latency (arrival), or the stream's while they run at the local clock's rate "
        "(auto)",
    )
    open_timeout_s: Annotated[float, Field(gt=0, le=120)] = Field(
        default=5.0, description="source = 'stream': give up opening after this long"
    )
    read_timeout_s: Annotated[float, Field(gt=0, le=120)] = Field(
        default=2.0, description="source = 'stream': no frame for this long = stream lost"
    )
    width: Annotated[int, Field(ge=16, le=4096)] = 640
    height: Annotated[int, Field(ge=16, le=4096)] = 480
    fps: Annotated[float, Field(gt=0, le=240)] = 30.0
    fourcc: str | None = Field(
        default=None, description="four-character code, e.g. 'YUYV' or 'MJPG'"
    )
    latency_frames: Annotated[int, Field(ge=0, le=10)] = Field(
        default=1, description="frames between exposure and delivery (measured by dffd calibrate)"
    )

    @field_validator("fourcc")
    @classmethod
    def _fourcc_four_chars(cls, value: str | None) -> str | None:
        if value is not None and not _FOURCC_RE.fullmatch(value):
            raise _value_error(f"{value!r} is not a four-character code such as 'YUYV' or 'MJPG'")
        return value

    @model_validator(mode="after")
    def _v4l2_needs_device(self) -> CaptureSection:
        if self.source == "v4l2" and self.device is None:
            raise _field_error(
                "device", "required when capture.source is 'v4l2' (e.g. /dev/video0 or 0)"
            )
        if self.source == "stream" and not self.url:
            raise _field_error(
                "url",
                "required when capture.source is 'stream' (e.g. rtsp://HOST:554/video1, "
                "http://HOST/video.mjpg or a video file)",
            )
        return self

    @property
    def latency(self) -> float:
        """Mid-exposure → delivery delay in seconds: ``latency_s``, else in frames / fps."""
        return self.latency_s if self.latency_s is not None else self.latency_frames / self.fps


class LensSection(_Section):
    """``[lens]``: the focus calibration table and the fixed zoom it was measured at."""

    file: Path = Field(
        default=Path(DEFAULT_LENS),
        description="lens calibration TOML, or the name of a packaged table (sim-evi-d100)",
    )
    zoom_counts: Annotated[int, Field(ge=0, le=0x4000)] | None = Field(
        default=None, description="VISCA zoom position; default: the calibration file's zoom_counts"
    )

    @field_validator("file")
    @classmethod
    def _packaged_table(cls, value: Path) -> Path:
        """A packaged table's name becomes its path; paths are resolved by load_config."""
        if not is_lens_name(value):
            return value
        try:
            return lens_table(str(value))
        except ResourceNotFoundError as exc:
            raise _value_error(str(exc)) from None


class SchedulerSection(_Section):
    """``[scheduler]``: when to take bursts, how to acquire and keep the target centred."""

    burst_policy: BurstPolicy = "every_n"
    burst_mode: BurstMode = Field(
        default="rolling",
        description="rolling: focus triangle lo, mid, hi, mid, …, a burst at every end; "
        "classic: mid → end → end → mid per burst",
    )
    burst_every_n_frames: Annotated[int, Field(ge=1, le=1000)] = 2
    sigma_threshold_m: Annotated[float, Field(gt=0, le=10)] = 0.05
    sigma_max_interval_frames: Annotated[int, Field(ge=1, le=10_000)] = Field(
        default=90,
        description="sigma policy: tracking frames between bursts while σ stays below threshold",
    )
    timing_margin_s: Annotated[float, Field(ge=0, le=0.1)] = Field(
        default=0.003, description="bound on frame-timestamp error when tagging frames, s"
    )
    initial_focus_depth_m: Annotated[float, Field(gt=0, le=1000)] = Field(
        default=4.0, description="focus depth while acquiring, before any estimate"
    )
    acquire_stable_frames: Annotated[int, Field(ge=0, le=100)] = Field(
        default=3, description="frames with a contour before bursts start (acquire first)"
    )
    pan_tilt_mode: PanTiltMode = "drive"
    pan_tilt_kp_per_s: Annotated[float, Field(ge=0, le=50)] = Field(
        default=1.5, description="proportional gain: angular rate per degree of centroid error"
    )
    pan_tilt_feedforward: bool = Field(
        default=True, description="add the target's angular velocity to the pan/tilt rate"
    )
    pan_tilt_deadband_px: Annotated[float, Field(ge=0, le=100)] = Field(
        default=16.0,
        description="hysteresis band: a correction starts when the projected error exceeds it, px",
    )
    pan_tilt_max_correction_deg_s: Annotated[float, Field(gt=0, le=300)] = Field(
        default=3.0,
        description="cap on correction speed minus target speed, deg/s (tracker: ±12 px/frame)",
    )
    pan_tilt_max_command_hz: Annotated[float, Field(gt=0, le=60)] = Field(
        default=10.0, description="cap on pan/tilt commands per second (they share the serial link)"
    )
    pan_tilt_lost_s: Annotated[float, Field(ge=0, le=60)] = Field(
        default=0.5, description="no contour this long: the target is lost (search starts)"
    )
    pan_tilt_search_s: Annotated[float, Field(ge=0, le=60)] = Field(
        default=2.0, description="follow the lost target's predicted path this long, then return"
    )
    search_after_s: Annotated[float, Field(ge=0, le=3600)] = Field(
        default=3.0,
        description=(
            "automatic acquisition that finds no target this long sweeps pan/tilt over the "
            "camera's range, s (0: never)"
        ),
    )
    search_retry_s: Annotated[float, Field(ge=0, le=86400)] = Field(
        default=60.0,
        description="a sweep that found nothing: hold where it began this long, then again, s",
    )


class EstimatorsSection(_Section):
    """``[estimators]``: which estimate is ``best`` and the noise model (docs/design.md §4)."""

    best: BestEstimator = "lpv"
    sigma_psi: Annotated[float, Field(gt=0, le=100)] = Field(
        default=0.05, description="σψ: noise intensity of the size-derived depth rate ψ_m"
    )
    sigma_beta: Annotated[float, Field(gt=0, le=100)] = Field(
        default=0.01, description="σβ: drift intensity of the bias β"
    )
    sigma_z: Annotated[float, Field(gt=0, le=100)] = Field(
        default=0.05, description="σz: noise intensity of the depth-from-focus measurement z_m"
    )
    lpv_rho_min_per_s: Annotated[float, Field(ge=-100, le=100)] = -2.0
    lpv_rho_max_per_s: Annotated[float, Field(ge=-100, le=100)] = 2.0
    focus_measure: FocusMeasure = Field(
        default="peak_gradient",
        description="focus cost of a burst frame: peak_gradient (the paper's), edge_variance "
        "(any PSF, noisier; docs/estimation.md §8) or debiased_peak (the peak gradient less its "
        "bias fitted online against the edge moment, §12)",
    )
    vertex_response: bool = Field(
        default=False,
        description="correct each burst's vertex by the lens file's vertex response (measured "
        "by dffd calibrate for the same focus measure; a lens file without one: no correction), "
        "its σ as fitted. Off by default: raw z_m 4-18 % better on the reference optics, but the "
        "published σ less honest (NEES up in most runs, 2σ coverage below 0.90 on all five "
        "scenarios' own seeds) and the best estimate no better (docs/estimation.md §29)",
    )

    @model_validator(mode="after")
    def _rho_range_ordered(self) -> EstimatorsSection:
        if self.lpv_rho_min_per_s >= self.lpv_rho_max_per_s:
            raise _field_error(
                "lpv_rho_max_per_s",
                f"must be greater than lpv_rho_min_per_s ({self.lpv_rho_min_per_s})",
            )
        return self


class TargetSection(_Section):
    """``[target]``: optional prior knowledge of the target."""

    known_size_m: Annotated[float, Field(gt=0, le=10)] | None = Field(
        default=None, description="real target size R; enables CF1"
    )
    roi: (
        tuple[
            Annotated[int, Field(ge=0)],
            Annotated[int, Field(ge=0)],
            Annotated[int, Field(gt=0)],
            Annotated[int, Field(gt=0)],
        ]
        | None
    ) = Field(default=None, description="initial region [x, y, w, h] in pixels to acquire")

    @field_validator("roi", mode="before")
    @classmethod
    def _roi_shape(cls, value: object) -> object:
        if value is not None and (not isinstance(value, list | tuple) or len(value) != 4):
            raise _value_error(
                f"{show_value(value)} is not [x, y, w, h]; "
                "give four integers in pixels, w and h > 0"
            )
        return value


@dataclass(frozen=True, slots=True)
class MqttEndpoint:
    """Where the MQTT client connects: host, port and whether TLS is used."""

    host: str
    port: int
    tls: bool
    embedded: bool


class MqttSection(_Section):
    """``[mqtt]``: the broker and the client's behaviour during outages."""

    url: str = Field(
        default="embedded", description="embedded | mqtt://host:port | mqtts://host:port"
    )
    topic_prefix: str = "dffd"
    username: str | None = None
    password_file: Path | None = Field(
        default=None, description="file holding the password (one line)"
    )
    ca_file: Path | None = None
    certfile: Path | None = None
    keyfile: Path | None = None
    embedded_port: Annotated[int, Field(ge=1, le=65535)] = DEFAULT_MQTT_PORT
    keepalive_s: Annotated[int, Field(ge=5, le=3600)] = 30
    backlog_max_messages: Annotated[int, Field(ge=0, le=1_000_000)] = Field(
        default=10_000,
        description="estimates/measurements kept while the broker is down (drop-oldest)",
    )
    queue_max_messages: Annotated[int, Field(ge=1, le=100_000)] = Field(
        default=1_000, description="outgoing queue between the daemon and the client (drop-oldest)"
    )
    reconnect_min_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    reconnect_max_s: Annotated[float, Field(gt=0, le=600)] = 30.0

    @field_validator("url")
    @classmethod
    def _url_form(cls, value: str) -> str:
        if value == "embedded":
            return value
        match = _MQTT_URL_RE.fullmatch(value)
        if match is None or not 1 <= int(match["port"] or DEFAULT_MQTT_PORT) <= 65535:
            raise _value_error(f"{value!r} is not embedded, mqtt://host:port or mqtts://host:port")
        return value

    @field_validator("topic_prefix")
    @classmethod
    def _prefix_form(cls, value: str) -> str:
        if not _TOPIC_PREFIX_RE.fullmatch(value):
            raise _value_error(
                f"{value!r} is not a usable topic prefix; use levels of letters, digits, '_',"
                " '-', '.' separated by '/', no wildcards and no leading or trailing '/'"
            )
        return value

    @model_validator(mode="after")
    def _consistent(self) -> MqttSection:
        if self.password_file is not None and self.username is None:
            raise _field_error("username", "required when mqtt.password_file is set")
        if (self.certfile is None) != (self.keyfile is None):
            missing = "keyfile" if self.keyfile is None else "certfile"
            raise _field_error(missing, "certfile and keyfile must be given together")
        tls_options = self.ca_file or self.certfile
        if tls_options is not None and not self.url.startswith("mqtts://"):
            raise _field_error(
                "url", "TLS options (ca_file/certfile/keyfile) need an mqtts://host:port url"
            )
        if self.reconnect_min_s > self.reconnect_max_s:
            raise _field_error(
                "reconnect_max_s", f"must be ≥ reconnect_min_s ({self.reconnect_min_s})"
            )
        return self

    @property
    def endpoint(self) -> MqttEndpoint:
        """The broker to connect to (the embedded one on loopback for ``url = "embedded"``)."""
        if self.url == "embedded":
            return MqttEndpoint(EMBEDDED_HOST, self.embedded_port, tls=False, embedded=True)
        match = _MQTT_URL_RE.fullmatch(self.url)
        assert match is not None  # checked by the validator
        tls = match["scheme"] == "mqtts"
        default_port = DEFAULT_MQTTS_PORT if tls else DEFAULT_MQTT_PORT
        host = match["host"].strip("[]")
        return MqttEndpoint(host, int(match["port"] or default_port), tls=tls, embedded=False)

    def read_password(self) -> str | None:
        """The password from ``password_file`` (first line, stripped), or None."""
        if self.password_file is None:
            return None
        try:
            text = self.password_file.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(
                [
                    (
                        f"mqtt.password_file: cannot read {self.password_file}: {exc.strerror}; "
                        "create it (mode 0600, owned by the service user) or unset it"
                    )
                ]
            ) from exc
        except UnicodeDecodeError as exc:
            raise ConfigError(
                [
                    (
                        f"mqtt.password_file: {self.password_file} is not UTF-8 text ({exc}); "
                        "write the password as one line of text"
                    )
                ]
            ) from exc
        lines = text.splitlines()
        return lines[0].strip() if lines else ""


class LogSection(_Section):
    """``[log]``: the durable JSONL log and the service's log level."""

    dir: Path = Field(
        default=Path("runs/log"), description="JSONL estimate/measurement log directory"
    )
    max_bytes: Annotated[int, Field(ge=4096, le=10 * 1024**3)] = 50 * 1024**2
    backup_count: Annotated[int, Field(ge=0, le=10_000)] = 20
    level: LogLevel = "INFO"

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value


class SimSection(_Section):
    """``[sim]``: the simulated camera and world used when camera.driver is 'sim'."""

    scenario: str = Field(
        default="paper-circle",
        description="a world shipped with the simulator (drivers/sim/data/worlds/<name>.toml, "
        "the worlds of the HIL scenarios of the same names, e.g. paper-circle) or the path of a "
        "TOML file with [target] and [trajectory] tables",
    )
    start_phase_deg: Annotated[float, Field(ge=-360, le=360)] | None = Field(
        default=180.0,
        description="overrides the trajectory's phase_deg (circle/figure-eight start point)",
    )
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] = 1
    camera_config: Path | None = Field(
        default=None, description="simulated camera TOML (default: built in)"
    )
    visca_transport: Literal["pty", "udp", "tcp"] = Field(
        default="pty",
        description="how the daemon reaches the simulated camera: pty = the serial path over a "
        "pseudo-terminal, udp = VISCA over IP on a loopback port, tcp = raw VISCA over TCP",
    )
    video: Literal["direct", "http"] = Field(
        default="direct",
        description="how the daemon gets the simulated camera's frames: direct = from its "
        "renderer, http = as MJPEG over HTTP on a loopback port, read like a network camera's "
        "stream (capture.latency_s applies)",
    )
    publish_truth: bool = True

    @field_validator("scenario")
    @classmethod
    def _scenario_form(cls, value: str) -> str:
        if value in world_names() or value.endswith(".toml"):
            return value
        raise _value_error(
            f"{value!r} is neither a simulated world ({', '.join(world_names())}) nor the path "
            "of a .toml world file"
        )

    @property
    def scenario_file(self) -> Path:
        """The world TOML: a packaged world's file (drivers/sim/data/worlds/), or the path."""
        if self.scenario in world_names():
            return world_file(self.scenario)
        return Path(self.scenario)


class WebSection(_Section):
    """``[web]``: the dashboard and Prometheus ``/metrics`` (off unless ``listen`` is set)."""

    listen: str | None = Field(
        default=None,
        description='"HOST:PORT" of the dashboard and /metrics; unset: off. Anything but a '
        "loopback address needs token_file",
    )
    token_file: Path | None = Field(
        default=None, description="file holding the bearer token the dashboard requires"
    )

    @field_validator("listen")
    @classmethod
    def _listen_form(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                parse_listen(value)
            except WebConfigError as exc:
                raise _value_error(str(exc).removeprefix(f"web.listen = {value!r}: ")) from None
        return value

    @model_validator(mode="after")
    def _token_beyond_loopback(self) -> WebSection:
        if self.listen is not None and self.token_file is None:
            host, _ = parse_listen(self.listen)
            if not is_loopback(host):
                raise _field_error(
                    "token_file",
                    f"listen = {self.listen!r} is not a loopback address: anyone on the network "
                    "could command the camera. Set web.token_file to a file holding a secret "
                    '(e.g. `openssl rand -hex 32 > FILE`) or listen on "127.0.0.1:PORT"',
                )
        return self


class DffdConfig(BaseSettings):
    """The whole configuration (docs/design.md §9); build it with :func:`load_config`."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        env_ignore_empty=True,  # an empty line in an EnvironmentFile template changes nothing
        env_parse_none_str="null",  # DFFD_TARGET__KNOWN_SIZE_M=null unsets an optional value
        extra="forbid",
        validate_default=True,
    )

    camera: CameraSection = CameraSection()
    capture: CaptureSection = CaptureSection()
    lens: LensSection = LensSection()
    scheduler: SchedulerSection = SchedulerSection()
    estimators: EstimatorsSection = EstimatorsSection()
    target: TargetSection = TargetSection()
    mqtt: MqttSection = MqttSection()
    log: LogSection = LogSection()
    sim: SimSection = SimSection()
    web: WebSection = WebSection()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Environment first (it wins), then the TOML data passed as init arguments."""
        return (env_settings, init_settings)

    @model_validator(mode="after")
    def _cross_section(self) -> DffdConfig:
        if self.estimators.best == "cf1" and self.target.known_size_m is None:
            raise PydanticCustomError(
                "dffd_path",
                "{message}",
                {
                    "path": "estimators.best",
                    "message": "'cf1' needs target.known_size_m; set it or choose lpv, kf or cf2",
                },
            )
        if self.camera.driver == "sim" and self.capture.source in ("v4l2", "stream"):
            raise PydanticCustomError(
                "dffd_path",
                "{message}",
                {
                    "path": "capture.source",
                    "message": f"{self.capture.source!r} cannot be used with the simulated "
                    "camera (camera.driver = 'sim'); use source = 'sim' (sim.video = 'http' "
                    "serves its frames as a network stream) or driver = 'visca'",
                },
            )
        if self.camera.driver == "visca" and self.capture.source == "sim":
            raise PydanticCustomError(
                "dffd_path",
                "{message}",
                {
                    "path": "capture.source",
                    "message": "'sim' needs camera.driver = 'sim' (the simulator renders what its "
                    "own camera sees); with a real camera use source = 'v4l2' and set "
                    "capture.device, or source = 'stream' and set capture.url",
                },
            )
        return self

    def to_toml(self) -> str:
        """The resolved configuration as TOML text (unset optional keys as comments)."""
        out: list[str] = []
        for section, values in self.model_dump(mode="json").items():
            if out:
                out.append("")
            out.append(f"[{section}]")
            for key, value in values.items():
                if value is None:
                    out.append(f"# {key} is unset")
                else:
                    out.append(f"{key} = {_toml_value(value)}")
        return "\n".join(out) + "\n"


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return json.dumps(str(value), ensure_ascii=False)
