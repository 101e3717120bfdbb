"""systemd/dffd.service: `systemd-analyze verify` is clean; the unit has what the service needs."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dffd.config import load_config

SYSTEMD_DIR = Path(__file__).resolve().parent.parent / "systemd"
UNIT = SYSTEMD_DIR / "dffd.service"
INSTALLED_DFFD = "/opt/dffd/venv/bin/dffd"
ANALYZE_PACKAGE = "systemd"  # Debian package that ships /usr/bin/systemd-analyze
# verify loads the unit and its dependencies offline: well under a second normally.
VERIFY_TIMEOUT_S = 60.0
# Installing the analyzer with apt when missing (only as root): a download + unpack.
INSTALL_TIMEOUT_S = 300.0


def _directives(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) for every line; keys may repeat (DeviceAllow, Environment)."""
    section = ""
    out = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.append((section, key.strip(), value.strip()))
    return out


def _values(key: str, section: str = "Service") -> list[str]:
    return [v for s, k, v in _directives(UNIT.read_text()) if s == section and k == key]


def _one(key: str, section: str = "Service") -> str:
    values = _values(key, section)
    assert len(values) == 1, f"{key}= should appear once in [{section}], found {values}"
    return values[0]


def _analyzer() -> str:
    found = shutil.which("systemd-analyze")
    if found:
        return found
    apt = shutil.which("apt-get")
    if apt is None or os.geteuid() != 0:
        pytest.skip(
            f"systemd-analyze is missing and cannot be installed here (not root or no apt-get); "
            f"install the Debian package {ANALYZE_PACKAGE!r} (`make system-deps`)"
        )
    env = os.environ | {"DEBIAN_FRONTEND": "noninteractive"}
    result = subprocess.run(
        [apt, "install", "-y", "-qq", "--no-install-recommends", ANALYZE_PACKAGE],
        capture_output=True,
        timeout=INSTALL_TIMEOUT_S,
        env=env,
        check=False,
    )
    found = shutil.which("systemd-analyze")
    if found is None:
        pytest.skip(f"installing {ANALYZE_PACKAGE!r} failed: {result.stderr.decode()[-500:]}")
    return found


def _verify(unit_text: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    # verify insists that ExecStart's binary exists: point it at this environment's dffd.
    here = Path(sys.executable).with_name("dffd")
    binary = str(here) if here.is_file() else "/bin/true"
    copy = tmp_path / "dffd.service"
    copy.write_text(unit_text.replace(INSTALLED_DFFD, binary), encoding="utf-8")
    return subprocess.run(
        [_analyzer(), "verify", str(copy)],
        capture_output=True,
        text=True,
        timeout=VERIFY_TIMEOUT_S,
        check=False,
    )


def test_unit_verifies_without_any_complaint(tmp_path: Path) -> None:
    result = _verify(UNIT.read_text(), tmp_path)
    # verify exits 0 on unknown keys and unparsable values (it only warns): treat any line
    # about our unit as a failure.
    complaints = [line for line in result.stderr.splitlines() if "dffd.service" in line]
    assert result.returncode == 0, result.stderr
    assert complaints == []


def test_verify_catches_a_broken_unit(tmp_path: Path) -> None:
    """The check above is meaningful: a typo and a bad value are reported."""
    broken = UNIT.read_text().replace("NoNewPrivileges=", "NoNewPrivilegs=")
    broken = broken.replace("WatchdogSec=10s", "WatchdogSec=ten")
    result = _verify(broken, tmp_path)
    assert "Unknown key 'NoNewPrivilegs'" in result.stderr
    assert "Failed to parse sec value" in result.stderr


def test_unit_runs_as_a_notify_service_with_watchdog() -> None:
    assert _one("Type") == "notify"
    assert _one("NotifyAccess") == "main"
    assert re.fullmatch(r"\d+s", _one("WatchdogSec"))
    assert _one("Restart") == "on-failure"
    assert re.fullmatch(r"\d+s", _one("TimeoutStopSec"))
    assert _one("ExecStart") == f"{INSTALLED_DFFD} run --config ${{DFFD_CONFIG}}"
    assert _one("EnvironmentFile") == "-/etc/dffd/dffd.env"
    assert "DFFD_CONFIG=/etc/dffd/dffd.toml" in _values("Environment")
    assert _one("WantedBy", "Install") == "multi-user.target"


def test_unit_is_confined_to_its_devices_and_state() -> None:
    assert _one("User") == "dffd"
    assert set(_one("SupplementaryGroups").split()) == {"dialout", "video"}
    for key, value in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "StateDirectory": "dffd",
        "DevicePolicy": "closed",
    }.items():
        assert _one(key) == value, key
    allowed = {v.split()[0] for v in _values("DeviceAllow")}
    assert {"/dev/visca0", "char-ttyUSB", "char-video4linux"} <= allowed


def test_sysusers_creates_the_service_user_in_both_groups() -> None:
    lines = [
        line.split()
        for line in (SYSTEMD_DIR / "dffd.sysusers.conf").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert lines[0][:2] == ["u", "dffd"]
    assert {tuple(line) for line in lines[1:]} == {("m", "dffd", "dialout"), ("m", "dffd", "video")}


def test_env_example_overrides_are_valid(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("DFFD_"):
            monkeypatch.delenv(name)
    for line in (SYSTEMD_DIR / "dffd.env.example").read_text().splitlines():
        match = re.fullmatch(r"#(DFFD_[A-Z_]+)=(.+)", line)
        if match:
            monkeypatch.setenv(match[1], match[2])
    config = load_config(None)  # raises ConfigError if an example names a bad key or value
    assert config.mqtt.url == "mqtt://broker.lab.internal:1883"
    assert config.target.known_size_m == 0.03576
