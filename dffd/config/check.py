"""``dffd check-config``, and the checks ``dffd run`` makes before it starts: the same list.

Validation (:func:`dffd.config.load_config`) catches every bad value and cross-field rule;
:func:`problems` adds what only the machine can tell — files the config names that do not exist,
and, when asked, the serial port and the video device. ``dffd run`` refuses a config with any of
them with exit code 2; ``dffd check-config`` (with ``--check-files`` for the devices, which are
often checked on another machine than the lab PC) reports them first, with the same code.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dffd.config.explain import ConfigError
from dffd.config.loading import load_config
from dffd.config.models import DffdConfig
from dffd.exitcodes import EXIT_OK, EXIT_USAGE
from drivers.visca.url import parse_camera_url

__all__ = ["check_run_config", "missing_devices", "problems", "run"]

# A V4L2 device given by index N is /dev/videoN.
_VIDEO_DEVICE = "/dev/video{}"


def check_run_config(path: Path | None) -> DffdConfig | str:
    """The config ``dffd run`` starts with, or the message (``dffd run: …``) that refuses it:
    a validation error or :func:`problems`, the devices included."""
    try:
        config = load_config(path)
    except ConfigError as exc:
        return f"dffd run: {exc}"
    missing = problems(config, devices=True)
    if missing:
        return "dffd run: " + "; ".join(missing)
    return config


def problems(config: DffdConfig, *, devices: bool) -> list[str]:
    """What stops ``dffd run`` beyond validation, one ``dotted.path: what to do`` line each.

    Files the config names must exist; with ``devices`` also the serial port of a VISCA camera
    and the V4L2 capture device.
    """
    named: list[tuple[str, Path | None]] = [
        ("lens.file", config.lens.file),
        ("mqtt.password_file", config.mqtt.password_file),
        ("mqtt.ca_file", config.mqtt.ca_file),
        ("mqtt.certfile", config.mqtt.certfile),
        ("mqtt.keyfile", config.mqtt.keyfile),
        ("sim.camera_config", config.sim.camera_config),
        ("sim.scenario", config.sim.scenario_file if config.camera.driver == "sim" else None),
        ("web.token_file", config.web.token_file),
    ]
    found = [
        f"{dotted}: {file} does not exist; create it or fix the path"
        for dotted, file in named
        if file is not None and not file.is_file()
    ]
    if devices:
        found.extend(missing_devices(config))
    return found


def missing_devices(config: DffdConfig) -> list[str]:
    """The local serial port and V4L2 device the config names that do not exist here, one
    ``dotted.path: what to do`` line each."""
    found = []
    port = config.camera.port
    if config.camera.driver == "visca" and port is not None:
        path = _serial_path(port)
        if path is not None and not path.exists():
            found.append(
                f"camera.port: {path} does not exist; plug in the adapter or fix the path "
                "(`dffd devices` lists serial adapters and prints a udev rule)"
            )
    device = config.capture.device
    if config.capture.source == "v4l2" and device is not None:
        path = Path(_VIDEO_DEVICE.format(device)) if isinstance(device, int) else Path(device)
        if not path.exists():
            found.append(
                f"capture.device: {path} does not exist; plug in the grabber or fix the device "
                "(`dffd devices` lists video devices)"
            )
    return found


def run(args: argparse.Namespace) -> int:
    """Validate ``args.file``; print the resolved config (stdout) or the problems (stderr)."""
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        print(f"dffd check-config: {exc}", file=sys.stderr)
        return EXIT_USAGE
    found = problems(config, devices=args.check_files)
    if found:
        error = ConfigError(found, str(args.file))
        print(f"dffd check-config: {error}", file=sys.stderr)
        return EXIT_USAGE
    absent = [] if args.check_files else missing_devices(config)
    if absent:
        # Valid as a file (it may be meant for another machine), but `dffd run` here refuses it.
        print(
            "dffd check-config: note: devices are checked only with --check-files; on this "
            "machine `dffd run` would stop with exit 2: " + "; ".join(absent),
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps(config.model_dump(mode="json"), indent=2))
    else:
        print(config.to_toml(), end="")
    return EXIT_OK


def _serial_path(port: str) -> Path | None:
    """The local device of a bare path or ``serial://PATH?…`` port; None for network ports and
    pyserial's URL handlers (``socket://…``)."""
    parsed = parse_camera_url(port)  # as the driver reads it; valid, the config checked it
    if parsed.transport != "serial" or "://" in parsed.target:
        return None
    return Path(parsed.target)
