"""Configuration: defaults, TOML, environment overrides, field-precise errors, check-config."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from dffd import cli
from dffd.config import (
    ConfigError,
    DffdConfig,
    MqttSection,
    WebSection,
    load_config,
)
from dffd.config import (
    problems as config_problems,
)
from dffd.resources import default_config_file, lens_table
from drivers.sim.resources import world_file

# The deployment examples of the source tree (the defaults are package data).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No DFFD_ variables leak in from the developer's shell; relative paths land in tmp."""
    for name in list(os.environ):
        if name.upper().startswith("DFFD_"):
            monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)


def write(tmp_path: Path, text: str, name: str = "dffd.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def problems(tmp_path: Path, text: str) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text))
    return info.value.problems


# -- defaults and files ------------------------------------------------------------------------


def test_defaults_are_the_simulated_embedded_run(tmp_path: Path) -> None:
    config = load_config(None)
    assert config.camera.name == "sim"
    assert config.camera.driver == "sim"
    assert config.camera.baudrate == 9600
    assert config.capture.source == "sim"
    assert config.mqtt.url == "embedded"
    assert config.mqtt.embedded_port == 1883
    assert config.mqtt.topic_prefix == "dffd"
    endpoint = config.mqtt.endpoint
    assert (endpoint.host, endpoint.port, endpoint.tls, endpoint.embedded) == (
        "127.0.0.1",
        1883,
        False,
        True,
    )
    assert config.sim.scenario == "paper-circle"
    assert config.estimators.best == "lpv"
    assert config.target.known_size_m is None
    assert config.lens.file == lens_table("sim-evi-d100")
    assert config.lens.file.is_file(), "the default lens table ships in dffd/defaults/lenses"
    assert config.log.dir == tmp_path / "runs" / "log"


def test_embedded_default_file_equals_the_fields_defaults(tmp_path: Path) -> None:
    assert default_config_file().parent.name == "defaults"
    # An empty file gets every field's own default: the embedded file must say the same, except
    # that the embedded run serves the dashboard (off unless a config file sets web.listen).
    embedded = load_config(None)
    assert embedded.web.listen == "127.0.0.1:8080"
    empty = load_config(write(tmp_path, ""))
    assert empty.web.listen is None
    assert empty == embedded.model_copy(update={"web": WebSection()})
    assert load_config(default_config_file()) == embedded


def test_shipped_lab_file_is_valid_hardware_config() -> None:
    config = load_config(CONFIG_DIR / "lab-evi-d100.toml")
    assert config.camera.driver == "visca"
    assert config.camera.port == "/dev/visca0"
    assert config.capture.source == "v4l2"
    assert config.capture.device == "/dev/video0"
    assert config.mqtt.endpoint.embedded is False
    assert config.mqtt.password_file == Path("/etc/dffd/mqtt-password")
    assert config.log.dir == Path("/var/lib/dffd")


def test_toml_values_and_relative_paths(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
[camera]
name = "evi2"
driver = "visca"
port = "/dev/ttyUSB0"
baudrate = 38400
address = 2
[capture]
source = "v4l2"
device = 1
fps = 25
[lens]
file = "lenses/mine.toml"
[target]
known_size_m = 0.03576
roi = [1, 2, 30, 40]
[estimators]
best = "cf1"
[mqtt]
url = "mqtts://broker.example:8884"
ca_file = "ca.pem"
[log]
dir = "logs"
""",
    )
    config = load_config(path)
    assert config.camera.address == 2
    assert config.capture.device == 1
    assert config.capture.fps == 25.0
    assert config.target.roi == (1, 2, 30, 40)
    assert config.lens.file == tmp_path / "lenses" / "mine.toml"  # relative to the file
    assert config.mqtt.ca_file == tmp_path / "ca.pem"
    assert config.log.dir == tmp_path / "logs"
    endpoint = config.mqtt.endpoint
    assert (endpoint.host, endpoint.port, endpoint.tls) == ("broker.example", 8884, True)


@pytest.mark.parametrize(
    ("url", "host", "port", "tls"),
    [
        ("mqtt://127.0.0.1:18883", "127.0.0.1", 18883, False),
        ("mqtt://broker", "broker", 1883, False),
        ("mqtts://broker", "broker", 8883, True),
        ("mqtt://[::1]:1884", "::1", 1884, False),
    ],
)
def test_mqtt_url_forms(url: str, host: str, port: int, tls: bool) -> None:
    endpoint = MqttSection(url=url).endpoint
    assert (endpoint.host, endpoint.port, endpoint.tls, endpoint.embedded) == (
        host,
        port,
        tls,
        False,
    )


# -- environment -------------------------------------------------------------------------------


def test_environment_wins_over_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, '[mqtt]\nurl = "mqtt://file:1883"\nkeepalive_s = 20\n')
    monkeypatch.setenv("DFFD_MQTT__URL", "mqtt://127.0.0.1:18883")
    monkeypatch.setenv("dffd_target__known_size_m", "0.05")  # case does not matter
    monkeypatch.setenv("DFFD_TARGET__ROI", "[5, 6, 7, 8]")
    monkeypatch.setenv("DFFD_LOG__DIR", "envlogs")
    monkeypatch.setenv("DFFD_CAMERA__PORT", "")  # empty: ignored
    config = load_config(path)
    assert config.mqtt.url == "mqtt://127.0.0.1:18883"
    assert config.mqtt.keepalive_s == 20  # the file's other keys survive
    assert config.target.known_size_m == 0.05
    assert config.target.roi == (5, 6, 7, 8)
    assert config.log.dir == tmp_path / "envlogs"  # relative env paths: the working directory
    assert config.camera.port is None


def test_environment_null_unsets(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, "[target]\nknown_size_m = 0.1\n")
    monkeypatch.setenv("DFFD_TARGET__KNOWN_SIZE_M", "null")
    assert load_config(path).target.known_size_m is None


def test_bad_environment_value_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DFFD_CAMERA__ADDRESS", "9")
    monkeypatch.setenv("DFFD_MQTT__URLL", "x")
    with pytest.raises(ConfigError) as info:
        load_config(None)
    found = info.value.problems
    assert any(
        p.startswith("camera.address: '9' is out of range; allowed: 1 ≤ address ≤ 7")
        and "DFFD_CAMERA__ADDRESS" in p
        for p in found
    ), found
    assert any(p.startswith("mqtt.urll: unknown key; did you mean 'url'?") for p in found), found


# -- every kind of bad field is named with its fix ---------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('[mqtt]\nurl = "mqtt:/x"\n',
         "mqtt.url: 'mqtt:/x' is not embedded, mqtt://host:port or mqtts://host:port"),
        ('[mqtt]\nurl = "mqtt://h:70000"\n', "mqtt.url: 'mqtt://h:70000' is not embedded"),
        ('[camera]\ndriver = "usb"\n', "camera.driver: 'usb' is not allowed; use 'sim' or 'visca'"),
        ("[camera]\nbaudrate = 19200\n", "camera.baudrate: 19200 is not allowed; use 9600"),
        ("[camera]\naddress = 0\n", "camera.address: 0 is out of range; allowed: 1 ≤ address ≤ 7"),
        ('[camera]\nname = "a/b"\n', "camera.name: 'a/b' is not a usable camera name"),
        ('[camera]\ndriver = "visca"\n', "camera.port: required when camera.driver is 'visca'"),
        ('[camera]\nport = "htp://cam"\n',
         "camera.port: 'htp://cam' is not a camera port: unknown scheme 'htp'"),
        ('[capture]\nwidth = "wide"\n', "capture.width: 'wide' is not an integer; allowed: 16"),
        ("[capture]\nfps = 0\n", "capture.fps: 0 is out of range; allowed: 0 < fps ≤ 240"),
        ("[capture]\nfps = nan\n", "capture.fps: nan is not a finite number"),
        ('[capture]\nfourcc = "MJPEG"\n', "capture.fourcc: 'MJPEG' is not a four-character code"),
        ('[camera]\ndriver = "visca"\nport = "/dev/ttyUSB0"\n[capture]\nsource = "v4l2"\n',
         "capture.device: required when capture.source is 'v4l2'"),
        ('[capture]\nsource = "v4l2"\ndevice = 0\n',
         "capture.source: 'v4l2' cannot be used with the simulated camera"),
        ('[scheduler]\nburst_policy = "often"\n',
         "scheduler.burst_policy: 'often' is not allowed; use 'every_n' or 'sigma'"),
        ("[scheduler]\nburst_every_n_frames = 0\n",
         "scheduler.burst_every_n_frames: 0 is out of range; allowed: 1 ≤"),
        ('[estimators]\nbest = "cf1"\n', "estimators.best: 'cf1' needs target.known_size_m"),
        ("[estimators]\nlpv_rho_min_per_s = 1.0\nlpv_rho_max_per_s = 1.0\n",
         "estimators.lpv_rho_max_per_s: must be greater than lpv_rho_min_per_s"),
        ("[target]\nknown_size_m = 0\n", "target.known_size_m: 0 is out of range; allowed: 0 <"),
        ("[target]\nroi = [1, 2, 3]\n", "target.roi: [1, 2, 3] is not [x, y, w, h]"),
        ('[mqtt]\npassword_file = "pw"\n', "mqtt.username: required when mqtt.password_file"),
        ('[mqtt]\nurl = "mqtts://h:8883"\ncertfile = "c.pem"\n',
         "mqtt.keyfile: certfile and keyfile must be given together"),
        ('[mqtt]\nurl = "mqtt://h:1883"\nca_file = "ca.pem"\n',
         "mqtt.url: TLS options (ca_file/certfile/keyfile) need an mqtts://host:port url"),
        ('[mqtt]\ntopic_prefix = "dffd/#"\n', "mqtt.topic_prefix: 'dffd/#' is not a usable"),
        ("[mqtt]\nreconnect_min_s = 5\nreconnect_max_s = 1\n",
         "mqtt.reconnect_max_s: must be ≥ reconnect_min_s"),
        ("[mqtt]\nembedded_port = 0\n", "mqtt.embedded_port: 0 is out of range; allowed: 1 ≤"),
        ('[log]\nlevel = "LOUD"\n', "log.level: 'LOUD' is not allowed; use 'DEBUG', 'INFO'"),
        ("[log]\nmax_bytes = 10\n", "log.max_bytes: 10 is out of range; allowed: 4096 ≤"),
        ('[sim]\nscenario = "circle"\n', "sim.scenario: 'circle' is neither a simulated world"),
        ('[sim]\nvisca_transport = "in-process"\n', "sim.visca_transport: 'in-process' is not"),
        ("[scheduler]\npan_tilt_ki_per_s2 = 0.1\n", "scheduler.pan_tilt_ki_per_s2: unknown key"),
        ('[sim]\npublish_truth = "maybe"\n', "sim.publish_truth: 'maybe' is not a boolean"),
        ("[sim]\nscneario = 1\n", "sim.scneario: unknown key; did you mean 'scenario'?"),
        ("[mqttt]\nurl = 1\n", "mqttt: unknown section; did you mean 'mqtt'?"),
        ("mqtt = 5\n", "mqtt: 5 is not a table; write it as a [mqtt] section"),
    ],
)  # fmt: skip
def test_bad_field_is_named_with_its_fix(tmp_path: Path, text: str, expected: str) -> None:
    found = problems(tmp_path, text)
    assert any(p.startswith(expected) for p in found), found


def test_all_problems_reported_at_once(tmp_path: Path) -> None:
    found = problems(tmp_path, "[camera]\naddress = 8\n[capture]\nfps = -1\n[log]\nlevel = 3\n")
    assert [p.split(":")[0] for p in found] == ["camera.address", "capture.fps", "log.level"]


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot read .*missing\.toml"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "[camera\nname = 1\n"))
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes('[camera]\nname = "caméra"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match="must be UTF-8"):
        load_config(latin1)


def test_missing_files_and_password(tmp_path: Path) -> None:
    secret = write(tmp_path, "hunter2\nignored\n", "pw")
    config = load_config(
        write(tmp_path, '[mqtt]\nusername = "u"\npassword_file = "pw"\n[lens]\nfile = "no.toml"\n')
    )
    assert config.mqtt.password_file == secret
    assert config.mqtt.read_password() == "hunter2"
    assert config_problems(config, devices=False) == [
        f"lens.file: {tmp_path / 'no.toml'} does not exist; create it or fix the path"
    ]
    secret.write_bytes(b"\xffpw\n")
    with pytest.raises(ConfigError, match=r"mqtt\.password_file: .* is not UTF-8"):
        config.mqtt.read_password()
    secret.unlink()
    with pytest.raises(ConfigError, match=r"mqtt\.password_file: cannot read"):
        config.mqtt.read_password()


# -- dffd check-config -------------------------------------------------------------------------


def test_check_config_prints_resolved_toml(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["check-config", str(default_config_file())]) == 0
    out = capsys.readouterr().out
    assert '[mqtt]\nurl = "embedded"' in out
    assert "# known_size_m is unset" in out
    assert DffdConfig(**tomllib.loads(out)) == load_config(None)  # the output round-trips


def test_check_config_json(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    path = write(tmp_path, "[capture]\nfps = 25\n")
    assert cli.main(["check-config", "--json", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)["capture"]["fps"] == 25.0


def test_check_config_invalid_exits_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    path = write(tmp_path, '[mqtt]\nurl = "mqtt:/x"\n')
    assert cli.main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "mqtt.url: 'mqtt:/x' is not embedded, mqtt://host:port or mqtts://host:port" in err


def test_check_config_missing_files_are_errors(capsys: pytest.CaptureFixture[str]) -> None:
    lab = str(CONFIG_DIR / "lab-evi-d100.toml")  # names /etc/dffd files absent here
    assert cli.main(["check-config", lab]) == 2
    err = capsys.readouterr().err
    assert "mqtt.password_file: /etc/dffd/mqtt-password does not exist" in err
    assert "warning" not in err


VISCA_V4L2 = (
    '[camera]\ndriver = "visca"\nport = "PORTURL"\n[capture]\nsource = "v4l2"\ndevice = "VIDEO"\n'
)


@pytest.mark.parametrize(
    ("text", "expected", "with_devices"),
    [
        # Cross-field rule: the simulator's frames need the simulated camera.
        ('[camera]\ndriver = "visca"\nport = "PORT"\n[capture]\nsource = "sim"\n',
         "capture.source: 'sim' needs camera.driver = 'sim'", False),
        ('[lens]\nfile = "absent.toml"\n', "lens.file: ", False),
        ('[lens]\nfile = "absent"\n', "lens.file: no packaged lens table 'absent'", False),
        (VISCA_V4L2.replace("PORTURL", "PORT"), "camera.port: ", True),
        (VISCA_V4L2.replace("PORTURL", "serial://PORT?baud=9600"), "capture.device: ", True),
    ],
)  # fmt: skip
def test_check_config_finds_what_stops_run_with_the_same_code(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    text: str,
    expected: str,
    with_devices: bool,
) -> None:
    port, video = tmp_path / "ttyUSB9", tmp_path / "video9"
    if "camera.port" not in expected:
        port.touch()  # only the device under test is missing
    if "capture.device" not in expected:
        video.touch()
    path = write(tmp_path, text.replace("PORT", str(port)).replace("VIDEO", str(video)))
    flags = ["--check-files"] if with_devices else []
    if with_devices:
        assert cli.main(["check-config", str(path)]) == 0  # devices: only on request…
        note = capsys.readouterr().err  # …but it says that run would refuse them here
        assert "only with --check-files" in note
        assert expected in note
    assert cli.main(["check-config", *flags, str(path)]) == 2
    assert expected in capsys.readouterr().err
    assert cli.main(["run", "--config", str(path), "--no-console"]) == 2  # refused alike
    assert expected in capsys.readouterr().err


# Camera ports of a new user's trial: each passed check-config, then `dffd run` died with a
# traceback (exit 1) or, for the last, looked for a serial adapter.
@pytest.mark.parametrize(
    ("port", "problem"),
    [
        ("tcp://127.0.0.1:notaport", "the port must be a number 1–65535"),
        ("visca-ip://", "it names no host"),
        ("serial:///dev/null?baud=abc", "baud must be a positive integer"),
        ("htp://127.0.0.1:5678", "unknown scheme 'htp' (did you mean 'tcp://127.0.0.1:5678'?)"),
        (
            "visca-ip//192.168.0.100",
            "it has no '://' after the scheme (did you mean 'visca-ip://192.168.0.100'?)",
        ),
    ],
)
def test_a_malformed_camera_port_is_refused_by_check_config_and_run_alike(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], port: str, problem: str
) -> None:
    video = tmp_path / "video9"
    video.touch()
    path = write(tmp_path, VISCA_V4L2.replace("PORTURL", port).replace("VIDEO", str(video)))
    expected = f"camera.port: {port!r} is not a camera port: {problem}"
    forms = "use a serial device (/dev/ttyUSB0, serial:///dev/visca0?baud=9600), visca-ip://"
    for argv in (["check-config", str(path)], ["run", "--config", str(path), "--no-console"]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert expected in err, argv
        assert forms in err, argv  # and the forms that work
        assert "does not exist" not in err  # not taken for a missing serial adapter


@pytest.mark.parametrize(
    ("port", "device"),
    [
        ("DIR/ttyUSB9", "DIR/ttyUSB9"),
        ("serial://DIR/visca9?baud=38400", "DIR/visca9"),
        ("visca-ip://192.168.0.100", None),
        ("tcp://192.168.0.100:5678", None),
        ("socket://192.168.0.100:4001", None),
        ("rfc2217://192.168.0.100:2217", None),
        ("loop://", None),
    ],
)
def test_every_documented_camera_port_loads_and_only_serial_devices_are_looked_for(
    tmp_path: Path, port: str, device: str | None
) -> None:
    port = port.replace("DIR", str(tmp_path))  # an absolute path: serial:// gets three slashes
    text = VISCA_V4L2.replace("PORTURL", port).replace("VIDEO", "/dev/null")
    config = load_config(write(tmp_path, text))
    assert config.camera.port == port
    missing = config_problems(config, devices=True)
    if device is None:
        assert missing == []
    else:
        assert missing == [
            (
                f"camera.port: {device.replace('DIR', str(tmp_path))} does not exist; plug in "
                "the adapter or fix the path (`dffd devices` lists serial adapters and prints a "
                "udev rule)"
            )
        ]


# A fresh interpreter's imports of the config (pydantic) take well under this; the daemon's take
# seconds on a busy machine.
RUN_REFUSAL_TIMEOUT_S = 60.0


def test_run_refuses_a_bad_config_before_it_loads_the_daemon(tmp_path: Path) -> None:
    path = write(tmp_path, "[scheduler]\nburst_every_n_frame = 2\n")
    probe = (
        "import sys; from dffd import cli; "
        f"rc = cli.main(['run', '--config', {str(path)!r}, '--no-console']); "
        "print(rc, 'dffd.daemon.app' in sys.modules, 'numba' in sys.modules, 'cv2' in sys.modules)"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True, text=True, timeout=RUN_REFUSAL_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert done.stdout.split() == ["2", "False", "False", "False"], done.stderr
    assert "did you mean 'burst_every_n_frames'?" in done.stderr


def test_scenario_is_a_packaged_world_or_a_path_next_to_the_file(tmp_path: Path) -> None:
    default = load_config(None)
    assert default.sim.scenario_file == world_file("paper-circle")
    assert default.sim.scenario_file.is_file()
    assert default.sim.start_phase_deg == 180.0  # the demo's fair start (dffd/defaults/dffd.toml)
    (tmp_path / "sub").mkdir()
    path = write(tmp_path / "sub", '[sim]\nscenario = "mine.toml"\n')
    config = load_config(path)
    assert config.sim.scenario_file == tmp_path / "sub" / "mine.toml"
    assert config_problems(config, devices=False) == [
        f"sim.scenario: {tmp_path / 'sub' / 'mine.toml'} does not exist; create it or fix the path"
    ]


def test_scheduler_keys_reach_their_defaults() -> None:
    sc = load_config(None).scheduler
    assert (sc.pan_tilt_mode, sc.pan_tilt_feedforward, sc.timing_margin_s) == ("drive", True, 0.003)
    assert (sc.pan_tilt_lost_s, sc.pan_tilt_search_s, sc.acquire_stable_frames) == (0.5, 2.0, 3)
