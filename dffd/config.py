"""Typed configuration: pydantic models loaded from TOML with ``DFFD_<SECTION>__<KEY>`` overrides.

DESIGN §9. ``load_config(path)`` is the only way the rest of the service gets its settings; every
field has a default and a range, unknown keys are errors, and a bad file produces a
:class:`ConfigError` that names each bad field by its dotted path (``mqtt.url``) and says what is
allowed. Environment variables win over the file (``DFFD_MQTT__URL=mqtt://127.0.0.1:18883``).

Relative paths written in a config file are resolved against that file's directory; relative
paths from the environment against the working directory. ``[lens] file`` may also name a lens
table shipped in the package (``sim-evi-d100``) and ``[sim] scenario`` a world shipped with the
simulator (``paper-circle``): see :mod:`dffd.resources` and :mod:`drivers.sim.resources`. All
paths are absolute after loading. Without a file, the embedded default
(``dffd/defaults/dffd.toml``, package data) is loaded.

This module is also the ``dffd check-config FILE`` subcommand (exit 0 valid, 2 invalid).
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import sys
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import annotated_types
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from dffd.resources import (
    DEFAULT_LENS,
    ResourceNotFoundError,
    default_config_file,
    is_lens_name,
    lens_table,
)
from dffd.web.listen import WebConfigError, is_loopback, parse_listen
from drivers.sim.resources import world_file, world_names

__all__ = [
    "ENV_PREFIX",
    "CameraConfig",
    "CaptureConfig",
    "ConfigError",
    "DffdConfig",
    "EstimatorsConfig",
    "LensConfig",
    "LogConfig",
    "MqttConfig",
    "MqttEndpoint",
    "SchedulerConfig",
    "SimConfig",
    "TargetConfig",
    "WebConfig",
    "configure_parser",
    "load_config",
    "missing_files",
    "run",
]

ENV_PREFIX = "DFFD_"
ENV_NESTED_DELIMITER = "__"

EXIT_OK = 0
EXIT_INVALID = 2

_CAMERA_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_TOPIC_PREFIX_RE = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")
_MQTT_URL_RE = re.compile(
    r"(?P<scheme>mqtts?)://(?P<host>\[[0-9A-Fa-f:.]+\]|[^:/\s\[\]@]+)(:(?P<port>\d{1,5}))?/?"
)
_FOURCC_RE = re.compile(r"[ -~]{4}")
DEFAULT_MQTT_PORT = 1883  # IANA port for MQTT
DEFAULT_MQTTS_PORT = 8883  # IANA port for MQTT over TLS
EMBEDDED_HOST = "127.0.0.1"  # the embedded broker never listens beyond loopback

EstimatorName = Literal["lpv", "kf", "cf2", "cf1"]
BurstPolicy = Literal["every_n", "sigma"]
BurstMode = Literal["rolling", "classic"]
PanTiltMode = Literal["drive", "absolute", "off"]
LogLevel = Literal["DEBUG", "INFO", "WARNING", "ERROR"]


class ConfigError(ValueError):
    """Invalid configuration; ``problems`` holds one ``dotted.path: what to do`` per field."""

    def __init__(self, problems: Sequence[str], source: str = "configuration") -> None:
        self.problems = list(problems)
        self.source = source
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"invalid {source}:\n{lines}")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True, allow_inf_nan=False)


def _field_error(field: str, message: str) -> PydanticCustomError:
    """A cross-field error reported at ``<section>.<field>`` rather than at the section."""
    return PydanticCustomError("dffd_field", "{message}", {"field": field, "message": message})


def _value_error(message: str) -> PydanticCustomError:
    return PydanticCustomError("dffd", "{message}", {"message": message})


class CameraConfig(_Section):
    """``[camera]``: which camera and how to reach it."""

    name: str = Field(default="sim", description="camera name, used in topics dffd/<name>/…")
    driver: Literal["sim", "visca"] = Field(default="sim", description="sim = simulated camera")
    port: str | None = Field(
        default=None, description="serial port of a VISCA camera, e.g. /dev/visca0"
    )
    baudrate: Literal[9600, 38400] = 9600
    address: Annotated[int, Field(ge=1, le=7)] = 1
    model: Literal["evi-d100", "evi-d70"] = "evi-d100"

    @field_validator("name")
    @classmethod
    def _name_is_topic_safe(cls, value: str) -> str:
        if not _CAMERA_NAME_RE.fullmatch(value):
            raise _value_error(
                f"{value!r} is not a usable camera name; use 1–64 letters, digits, '_', '-' or '.'"
                " (it becomes an MQTT topic level)"
            )
        return value

    @model_validator(mode="after")
    def _visca_needs_port(self) -> CameraConfig:
        if self.driver == "visca" and not self.port:
            raise _field_error(
                "port", "required when camera.driver is 'visca' (e.g. /dev/visca0 or /dev/ttyUSB0)"
            )
        return self


class CaptureConfig(_Section):
    """``[capture]``: the frame source."""

    source: Literal["sim", "v4l2"] = "sim"
    device: str | Annotated[int, Field(ge=0)] | None = Field(
        default=None, description="v4l2 device path (/dev/video0) or index"
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
    def _v4l2_needs_device(self) -> CaptureConfig:
        if self.source == "v4l2" and self.device is None:
            raise _field_error(
                "device", "required when capture.source is 'v4l2' (e.g. /dev/video0 or 0)"
            )
        return self


class LensConfig(_Section):
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


class SchedulerConfig(_Section):
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


class EstimatorsConfig(_Section):
    """``[estimators]``: which estimate is ``best`` and the noise model (DESIGN §3)."""

    best: EstimatorName = "lpv"
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

    @model_validator(mode="after")
    def _rho_range_ordered(self) -> EstimatorsConfig:
        if self.lpv_rho_min_per_s >= self.lpv_rho_max_per_s:
            raise _field_error(
                "lpv_rho_max_per_s",
                f"must be greater than lpv_rho_min_per_s ({self.lpv_rho_min_per_s})",
            )
        return self


class TargetConfig(_Section):
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
                f"{_show(value)} is not [x, y, w, h]; give four integers in pixels, w and h > 0"
            )
        return value


@dataclass(frozen=True, slots=True)
class MqttEndpoint:
    """Where the MQTT client connects: host, port and whether TLS is used."""

    host: str
    port: int
    tls: bool
    embedded: bool


class MqttConfig(_Section):
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
    def _consistent(self) -> MqttConfig:
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


class LogConfig(_Section):
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


class SimConfig(_Section):
    """``[sim]``: the simulated camera and world used when camera.driver is 'sim'."""

    scenario: str = Field(
        default="paper-circle",
        description="a simulated world shipped with the simulator (static, approach, "
        "paper-circle, figure-eight, random: drivers/sim/data/worlds/) or the path of a TOML "
        "file with [target] and [trajectory] tables",
    )
    start_phase_deg: Annotated[float, Field(ge=-360, le=360)] | None = Field(
        default=180.0,
        description="overrides the trajectory's phase_deg (circle/figure-eight start point)",
    )
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] = 1
    camera_config: Path | None = Field(
        default=None, description="simulated camera TOML (default: built in)"
    )
    visca_transport: Literal["pty"] = Field(
        default="pty", description="pty = the real serial path over a pseudo-terminal (only one)"
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


class WebConfig(_Section):
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
    def _token_beyond_loopback(self) -> WebConfig:
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
    """The whole configuration (DESIGN §9); build it with :func:`load_config`."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        env_ignore_empty=True,  # an empty line in an EnvironmentFile template changes nothing
        env_parse_none_str="null",  # DFFD_TARGET__KNOWN_SIZE_M=null unsets an optional value
        extra="forbid",
        validate_default=True,
    )

    camera: CameraConfig = CameraConfig()
    capture: CaptureConfig = CaptureConfig()
    lens: LensConfig = LensConfig()
    scheduler: SchedulerConfig = SchedulerConfig()
    estimators: EstimatorsConfig = EstimatorsConfig()
    target: TargetConfig = TargetConfig()
    mqtt: MqttConfig = MqttConfig()
    log: LogConfig = LogConfig()
    sim: SimConfig = SimConfig()
    web: WebConfig = WebConfig()

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
        if self.camera.driver == "sim" and self.capture.source == "v4l2":
            raise PydanticCustomError(
                "dffd_path",
                "{message}",
                {
                    "path": "capture.source",
                    "message": "'v4l2' cannot be used with the simulated camera "
                    "(camera.driver = 'sim'); use source = 'sim' or driver = 'visca'",
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


def load_config(path: Path | None = None) -> DffdConfig:
    """Load ``path`` (None: the embedded default) plus ``DFFD_…`` environment overrides.

    Raises ConfigError naming every bad field by its dotted path and saying what is allowed.
    """
    source = str(path) if path is not None else "embedded default configuration"
    file = path if path is not None else default_config_file()
    data = _read_toml(file)
    try:
        config = DffdConfig(**data)
    except ValidationError as exc:
        raise ConfigError(list(_describe_errors(exc, data)), source) from None
    return _resolve_paths(config, data, file.resolve().parent)


def missing_files(config: DffdConfig) -> list[str]:
    """Files the configuration names that do not exist here, as ``dotted.path: message`` lines."""
    named: list[tuple[str, Path | None]] = [
        ("lens.file", config.lens.file),
        ("mqtt.password_file", config.mqtt.password_file),
        ("mqtt.ca_file", config.mqtt.ca_file),
        ("mqtt.certfile", config.mqtt.certfile),
        ("mqtt.keyfile", config.mqtt.keyfile),
        ("sim.camera_config", config.sim.camera_config),
        ("sim.scenario", config.sim.scenario_file),
        ("web.token_file", config.web.token_file),
    ]
    return [
        f"{dotted}: {file} does not exist; create it or fix the path"
        for dotted, file in named
        if file is not None and not file.is_file()
    ]


# -- dffd check-config ------------------------------------------------------------------------


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dffd check-config``."""
    parser.add_argument("file", type=Path, metavar="FILE", help="TOML configuration file")
    parser.add_argument(
        "--json", action="store_true", help="print the resolved configuration as JSON"
    )
    parser.add_argument(
        "--check-files",
        action="store_true",
        help="also fail (exit 2) when a file the config names (lens table, password…) is missing",
    )
    parser.epilog = (
        f"Environment variables {ENV_PREFIX}<SECTION>__<KEY> override the file. "
        "Exit codes: 0 valid, 2 invalid."
    )


def run(args: argparse.Namespace) -> int:
    """Validate ``args.file``; print the resolved config (stdout) or the errors (stderr)."""
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        print(f"dffd check-config: {exc}", file=sys.stderr)
        return EXIT_INVALID
    absent = missing_files(config)
    for line in absent:
        print(f"dffd check-config: warning: {line}", file=sys.stderr)
    if args.json:
        print(json.dumps(config.model_dump(mode="json"), indent=2))
    else:
        print(config.to_toml(), end="")
    return EXIT_INVALID if absent and args.check_files else EXIT_OK


# -- private helpers --------------------------------------------------------------------------


_PATH_FIELDS: tuple[tuple[str, str], ...] = (
    ("lens", "file"),
    ("mqtt", "password_file"),
    ("mqtt", "ca_file"),
    ("mqtt", "certfile"),
    ("mqtt", "keyfile"),
    ("log", "dir"),
    ("sim", "camera_config"),
    ("web", "token_file"),
)


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(
            [f"cannot read {path}: {exc.strerror}; check the path"],
            str(path),
        ) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            [f"not valid TOML: {exc} (a TOML file must be UTF-8 text; re-save it as UTF-8)"],
            str(path),
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"not valid TOML: {exc}"], str(path)) from None


def _resolve_paths(config: DffdConfig, data: Mapping[str, Any], base: Path) -> DffdConfig:
    """Make every path absolute: file values against ``base``, env/defaults against the cwd."""
    updates: dict[str, BaseModel] = {}
    for section, key in _PATH_FIELDS:
        model: BaseModel = updates.get(section) or getattr(config, section)
        value = getattr(model, key)
        if value is None:
            continue
        value = Path(value).expanduser()
        if not value.is_absolute():
            from_file = isinstance(data.get(section), dict) and key in data[section]
            from_env = _env_name(section, key) in _environ_upper()
            anchor = base if from_file and not from_env else Path.cwd()
            value = anchor / value
        updates[section] = model.model_copy(update={key: value})
    sim: SimConfig = updates.get("sim") or config.sim  # type: ignore[assignment]
    if sim.scenario not in world_names() and not Path(sim.scenario).is_absolute():
        from_file = isinstance(data.get("sim"), dict) and "scenario" in data["sim"]
        from_env = _env_name("sim", "scenario") in _environ_upper()
        anchor = base if from_file and not from_env else Path.cwd()
        resolved = str(anchor / Path(sim.scenario).expanduser())
        updates["sim"] = sim.model_copy(update={"scenario": resolved})
    return config.model_copy(update=updates)


def _environ_upper() -> set[str]:
    return {name.upper() for name in os.environ}


def _env_name(section: str, key: str) -> str:
    return f"{ENV_PREFIX}{section}{ENV_NESTED_DELIMITER}{key}".upper()


def _describe_errors(exc: ValidationError, data: Mapping[str, Any]) -> Iterator[str]:
    env = _environ_upper()
    for error in exc.errors(include_url=False):
        loc = tuple(str(part) for part in error["loc"])
        ctx = error.get("ctx") or {}
        if error["type"] == "dffd_path":
            loc = tuple(str(ctx["path"]).split("."))
        elif error["type"] == "dffd_field":
            loc = (*loc, str(ctx["field"]))
        path = ".".join(loc) or "(top level)"
        line = f"{path}: {_explain(error, loc)}"
        if len(loc) >= 2 and _env_name(loc[0], loc[1]) in env:
            line += f" (from environment variable {_env_name(loc[0], loc[1])})"
        elif len(loc) == 1 and loc[0] not in data and error["type"] == "extra_forbidden":
            line += " (from the environment)"
        yield line


def _explain(error: Any, loc: tuple[str, ...]) -> str:
    kind: str = error["type"]
    value = error.get("input")
    ctx = error.get("ctx") or {}
    shown = _show(value)
    if kind in {"dffd", "dffd_field", "dffd_path"}:
        return str(ctx["message"])
    if kind == "extra_forbidden":
        return _unknown_key(loc)
    if kind == "literal_error":
        return f"{shown} is not allowed; use {ctx['expected']}"
    if kind in {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}:
        return f"{shown} is out of range; {_range_text(loc) or error['msg'].lower()}"
    if kind in {"int_parsing", "int_type", "int_from_float"}:
        return f"{shown} is not an integer; {_range_text(loc) or 'give a whole number'}"
    if kind in {"float_parsing", "float_type", "finite_number"}:
        return f"{shown} is not a finite number; {_range_text(loc) or 'give a number'}"
    if kind in {"bool_parsing", "bool_type"}:
        return f"{shown} is not a boolean; use true or false"
    if kind in {"string_type", "path_type"}:
        return f'{shown} is not text; quote it, e.g. "..."'
    if kind in {"model_type", "model_attributes_type", "dict_type"}:
        return f"{shown} is not a table; write it as a [{loc[0]}] section with keys"
    if kind in {"tuple_type", "list_type", "too_short", "too_long"}:
        return f"{shown} has the wrong shape; {error['msg'].lower()}"
    return f"{error['msg']} (got {shown})"


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _unknown_key(loc: tuple[str, ...]) -> str:
    if len(loc) == 1:
        valid = list(DffdConfig.model_fields)
        what, where = "unknown section", "valid sections"
    else:
        section_field = DffdConfig.model_fields.get(loc[0])
        annotation = section_field.annotation if section_field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return "unknown key"
        valid = list(annotation.model_fields)
        what, where = "unknown key", f"valid keys in [{loc[0]}]"
    close = difflib.get_close_matches(loc[-1], valid, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"{what}{hint} ({where}: {', '.join(valid)})"


def _range_text(loc: tuple[str, ...]) -> str:
    """'allowed: 1 ≤ fps ≤ 240' from the field's declared bounds, or '' if it has none."""
    if len(loc) < 2:
        return ""
    section_field = DffdConfig.model_fields.get(loc[0])
    annotation = section_field.annotation if section_field is not None else None
    if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
        return ""
    info = annotation.model_fields.get(loc[1])
    if info is None:
        return ""
    low = high = ""
    for meta in _bounds_metadata(info.metadata, info.annotation):
        if isinstance(meta, annotated_types.Ge):
            low = f"{meta.ge} ≤ "
        elif isinstance(meta, annotated_types.Gt):
            low = f"{meta.gt} < "
        elif isinstance(meta, annotated_types.Le):
            high = f" ≤ {meta.le}"
        elif isinstance(meta, annotated_types.Lt):
            high = f" < {meta.lt}"
    if not (low or high):
        return ""
    return f"allowed: {low}{loc[1]}{high}"


def _bounds_metadata(metadata: list[Any], annotation: Any) -> list[Any]:
    """Bounds declared on the field itself or inside an ``Annotated[...] | None`` annotation."""
    found = list(metadata)
    for arg in getattr(annotation, "__args__", ()):
        found.extend(getattr(arg, "__metadata__", ()))
    for meta in list(found):
        found.extend(getattr(meta, "metadata", ()))  # FieldInfo inside Annotated
    return found


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return json.dumps(str(value), ensure_ascii=False)
