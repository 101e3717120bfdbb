"""The arguments of every ``dffd`` subcommand, in one place and without heavy imports.

``dffd SUBCOMMAND --help`` builds its parser from here alone: nothing in this module imports
NumPy, OpenCV, SciPy, numba, pydantic or the subcommand's implementation, so help is instant.
The implementations receive the parsed :class:`argparse.Namespace`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dffd.exitcodes import EXIT_CODES_HELP

__all__ = [
    "REPLAY_ESTIMATORS",
    "configure_calibrate",
    "configure_check_config",
    "configure_devices",
    "configure_replay",
    "configure_run",
]

# dffd.core.pipeline.ESTIMATORS (a test keeps them equal; importing the core here would load
# SciPy and numba for --help).
REPLAY_ESTIMATORS = ("measured", "cf1", "cf2", "lpv", "kf")
# drivers.usb's DEFAULT_LINK_NAME, DEFAULT_GROUP and SYSFS_USB (importing it loads pyusb).
DEVICES_LINK_NAME = "visca0"
DEVICES_GROUP = "dialout"
DEVICES_SYSFS = Path("/sys/bus/usb/devices")


def configure_run(parser: argparse.ArgumentParser) -> None:
    """``dffd run``."""
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="TOML configuration (default: built-in: simulated camera, embedded broker)",
    )
    parser.add_argument(
        "--no-console",
        action="store_true",
        help="no live console view; log a status line every second instead",
    )
    parser.add_argument(
        "--sim-faults",
        metavar="SPEC",
        default="",
        help="seeded serial faults in the simulated camera (tests, demos), e.g. "
        '"seed=3,drop=0.01,lose_completion=0.05" (keys as dffd sim-camera --faults)',
    )
    parser.add_argument(
        "--duration",
        type=float,
        metavar="SECONDS",
        help="stop by itself after this many seconds (demos, benchmarks)",
    )
    parser.epilog = EXIT_CODES_HELP


def configure_replay(parser: argparse.ArgumentParser) -> None:
    """``dffd replay``."""
    parser.add_argument("run", type=Path, help="recording directory (meta.json, frames.csv, …)")
    parser.add_argument("--out", type=Path, required=True, help="estimates, one JSON per line")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="service config TOML whose [estimators]/[target] configure the core "
        "(default: the built-in default configuration, as dffd run)",
    )
    parser.add_argument("--summary", type=Path, help="write the error summary (needs truth.csv)")
    parser.add_argument("--plot", type=Path, help="write a PNG plot of depths and errors")
    parser.add_argument(
        "--settle",
        type=float,
        default=None,
        help="settling time (s) before steady-state statistics (default 5)",
    )
    parser.add_argument(
        "--known-size",
        type=float,
        default=None,
        metavar="M",
        help="target size in metres (enables CF1; default: [target] known_size_m)",
    )
    parser.add_argument(
        "--best",
        choices=REPLAY_ESTIMATORS,
        default=None,
        help="estimator reported as best (default: [estimators] best)",
    )
    parser.add_argument(
        "--roi",
        default=None,
        metavar="X,Y,W,H",
        help="acquire the target inside this ROI instead of automatically (default: [target] roi)",
    )
    parser.epilog = EXIT_CODES_HELP


def configure_calibrate(parser: argparse.ArgumentParser) -> None:
    """``dffd calibrate``."""
    parser.add_argument(
        "--config", type=Path, metavar="FILE",
        help="lab procedure: the service config naming camera.port, capture.device and "
        "lens.file (its focal length and pixel pitch are reused if it exists, else the packaged "
        "sim-evi-d100's); an operator places the target at each depth",
    )  # fmt: skip
    parser.add_argument("--sim", action="store_true", help="calibrate the simulated camera")
    parser.add_argument(
        "--sim-config", type=Path, default=None, metavar="FILE",
        help="simulated-camera TOML (default: the reference camera in drivers/sim/data/)",
    )  # fmt: skip
    parser.add_argument(
        "--depths", default=None, metavar="Z1,Z2,…",
        help="known target depths in metres (default: 23 depths from 1 to 20 m, every "
        "0.25-0.75 m over 2-10 m; with --sim each depth moved out to where the simulated "
        "target fits the tracker: 1.2 m to 20 m)",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, metavar="FILE",
        help="write the lens TOML here (its directory must exist; checked before the first depth)",
    )  # fmt: skip
    parser.add_argument("--name", default="calibrated", help="lens name in the TOML file")
    parser.add_argument(
        "--latency", action="store_true",
        help="measure the video latency of --config's camera and video ([capture] latency_s) "
        "by small pan steps (2° each; the first frame that shows a step), instead of the focus "
        "table",
    )  # fmt: skip
    parser.add_argument(
        "--trials", type=int, default=None, metavar="N",
        help="pan steps for --latency, their median is the latency (default: 15)",
    )  # fmt: skip
    parser.description = (
        "Fit the focus counts <-> v table from focus sweeps with the target at known depths and "
        "measure the capture latency. --sim: the simulated camera. --config FILE: the real "
        "camera (serial port + video device of FILE); you are prompted at the terminal to place "
        "the target at each depth. Same procedure either way (docs/design.md §3.1)."
    )
    parser.epilog = (
        "Exit codes: 0 written, 1 calibration failed, 2 usage/config error (also --config "
        "without a terminal on stdin), 130 stopped (Ctrl-C; Ctrl-D at a prompt)."
    )


def configure_check_config(parser: argparse.ArgumentParser) -> None:
    """``dffd check-config``."""
    parser.add_argument("file", type=Path, metavar="FILE", help="TOML configuration file")
    parser.add_argument(
        "--json", action="store_true", help="print the resolved configuration as JSON"
    )
    parser.add_argument(
        "--check-files",
        action="store_true",
        help="also check the serial port and video device the config names exist here "
        "(files it names — lens table, password, certificates — are always checked)",
    )
    parser.epilog = (
        "Environment variables DFFD_<SECTION>__<KEY> override the file. Exit codes: 0 valid, "
        "2 invalid (the same problems make `dffd run` exit 2)."
    )


def configure_devices(parser: argparse.ArgumentParser) -> None:
    """``dffd devices`` (implementation: drivers.usb)."""
    parser.add_argument(
        "--name",
        default=DEVICES_LINK_NAME,
        help=f"symlink the udev rule creates in /dev (default {DEVICES_LINK_NAME})",
    )
    parser.add_argument(
        "--group",
        default=DEVICES_GROUP,
        help=f"group owning the serial port (default {DEVICES_GROUP})",
    )
    parser.add_argument("--sysfs-root", type=Path, default=DEVICES_SYSFS, help=argparse.SUPPRESS)
