"""The ``dffd`` command line: a thin dispatcher to one module per subcommand.

Each subcommand module exposes ``configure_parser(parser)`` and ``run(args) -> int``; modules are
imported lazily so ``dffd --help`` and light commands start fast and do not pull in OpenCV.

Exit codes (documented in README.md):
  0  success
  1  runtime failure (the camera, broker or recording could not be used; the message says why)
  2  usage or configuration error (bad arguments, invalid config file)
  130 interrupted by the user before start-up finished
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from typing import Protocol, cast

from dffd import __version__

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("dffd.daemon.app", "run the service (no config: simulated camera, embedded broker)"),
    "sim-camera": ("drivers.sim.cli", "serve the simulated VISCA camera on a pseudo-terminal"),
    "replay": ("dffd.replay", "run the estimation core on a recording"),
    "devices": ("drivers.usb", "list USB serial bridges and video devices, print a udev rule"),
    "calibrate": ("dffd.calibrate", "fit the focus table and measure the capture latency"),
    "check-config": ("dffd.config", "validate a config file and print the resolved config"),
}


class _Subcommand(Protocol):
    def configure_parser(self, parser: argparse.ArgumentParser) -> None: ...

    def run(self, args: argparse.Namespace) -> int: ...


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level parser; only the ``selected`` subcommand's module is imported."""
    parser = argparse.ArgumentParser(
        prog="dffd",
        description="Depth-from-focus daemon for VISCA pan/tilt/focus cameras.",
        epilog="Exit codes: 0 ok, 1 runtime failure, 2 usage/config error, 130 interrupted.",
    )
    parser.add_argument("--version", action="version", version=f"dffd {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        sub.set_defaults(_module=module_name)
        if name == selected:
            _load(module_name).configure_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen subcommand; return its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((arg for arg in argv if arg in SUBCOMMANDS), None)
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return _load(args._module).run(args)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


def entry_point() -> None:
    """Console-script entry point."""
    sys.exit(main())


def _load(module_name: str) -> _Subcommand:
    return cast(_Subcommand, importlib.import_module(module_name))
