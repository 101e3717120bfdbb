"""The ``dffd`` command line: every subcommand registered here, in one table.

A subcommand is its arguments (in ``dffd.cli.arguments``; ``sim-camera``'s in its own module
``drivers.sim.cli``) and an implementation ``run(args) -> int``, imported only to run it, so
``dffd … --help`` loads neither OpenCV, SciPy, numba nor pydantic. Exit codes:
:mod:`dffd.exitcodes`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast

from dffd import __version__
from dffd.exitcodes import EXIT_CODES_HELP, EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE

__all__ = [
    "SUBCOMMANDS",
    "Subcommand",
    "build_parser",
    "entry_point",
    "main",
    "service_log_level",
    "verbosity_level",
]


@dataclass(frozen=True, slots=True)
class Subcommand:
    """One subcommand: its help line, where its arguments and its implementation live."""

    help: str
    arguments: str  # "module:function(parser)"
    implementation: str  # "module:function(args) -> exit code"


SUBCOMMANDS: dict[str, Subcommand] = {
    "run": Subcommand(
        "run the service (no config: simulated camera, embedded broker)",
        "dffd.cli.arguments:configure_run",
        "dffd.daemon.cli:run",
    ),
    "sim-camera": Subcommand(
        "serve the simulated VISCA camera on a pseudo-terminal, TCP or UDP (--listen)",
        "drivers.sim.cli:configure_parser",
        "drivers.sim.cli:run",
    ),
    "replay": Subcommand(
        "run the estimation core on a recording",
        "dffd.cli.arguments:configure_replay",
        "dffd.replay:run",
    ),
    "devices": Subcommand(
        "list USB serial bridges and video devices, print a udev rule",
        "dffd.cli.arguments:configure_devices",
        "drivers.usb:run",
    ),
    "calibrate": Subcommand(
        "fit the focus table and measure the capture latency",
        "dffd.cli.arguments:configure_calibrate",
        "dffd.calibrate:run",
    ),
    "check-config": Subcommand(
        "validate a config file and print the resolved config",
        "dffd.cli.arguments:configure_check_config",
        "dffd.config.check:run",
    ),
}


# The root logger's level for no -v, -v and -vv (more v's: still DEBUG).
_VERBOSITY_LEVELS = (logging.WARNING, logging.INFO, logging.DEBUG)


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser; only the ``selected`` subcommand's arguments are loaded."""
    parser = argparse.ArgumentParser(
        prog="dffd",
        description="Depth-from-focus daemon for VISCA pan/tilt/focus cameras.",
        epilog=EXIT_CODES_HELP,
    )
    parser.add_argument("--version", action="version", version=f"dffd {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, sub in SUBCOMMANDS.items():
        sub_parser = subparsers.add_parser(name, help=sub.help, description=sub.help)
        sub_parser.set_defaults(_implementation=sub.implementation)
        if name == selected:
            _resolve(sub.arguments)(sub_parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen subcommand; return its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((arg for arg in argv if arg in SUBCOMMANDS), None)
    args = build_parser(selected).parse_args(argv)
    logging.basicConfig(
        level=verbosity_level(args.verbose),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    warm = None
    if args.command == "run":
        from dffd.config import check_run_config

        # before the daemon's imports and the kernels' warm-up (a second or more on a busy
        # machine): a typo is reported at once, and nothing starts for a config that cannot run
        checked = check_run_config(args.config)
        if isinstance(checked, str):
            print(checked, file=sys.stderr)
            return EXIT_USAGE
        args.checked_config = checked
    if args.command == "run":
        from dffd.cli.loading import say_if_compiling
        from dffd.warmup import start_background

        # The service starts on the kernels' NumPy twins while numba compiles in a separate
        # process (seconds to a first estimate on a fresh install, not ~30 s). Replay and
        # calibrate wait for the compiled kernels (their results must not depend on timing)
        # and say so themselves, once they have checked their inputs.
        say_if_compiling("run", background=True)
        warm = start_background()
    try:
        return cast(int, _resolve(args._implementation)(args))
    except KeyboardInterrupt:
        # Ctrl-C before the subcommand could handle it (e.g. `dffd run` still loading).
        print(f"\ndffd {args.command}: interrupted (exit {EXIT_INTERRUPTED})", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if warm is not None:
            warm.stop()


def verbosity_level(verbose: int) -> int:
    """The logging level ``-v`` given ``verbose`` times asks for: WARNING, INFO, DEBUG (-vv)."""
    return _VERBOSITY_LEVELS[min(verbose, len(_VERBOSITY_LEVELS) - 1)]


def service_log_level(configured: str, verbose: int) -> int:
    """The level of dffd's own loggers: ``[log] level``, or the command line's when ``-v`` is
    given and asks for more (the more verbose of the two)."""
    level = logging.getLevelNamesMapping()[configured]
    return min(level, verbosity_level(verbose)) if verbose else level


def entry_point() -> None:
    """Console-script entry point; exit 1 quietly when stdout's reader has gone (``| head``)."""
    try:
        try:
            code: str | int | None = main()
        except SystemExit as exc:  # argparse: --help, --version, a usage error
            code = exc.code
        sys.stdout.flush()  # here, not at the interpreter's exit, where it could not be caught
    except BrokenPipeError:
        # As the Python docs advise (signal module, "Note on SIGPIPE"): point stdout at devnull,
        # so that the flush at exit does not raise again, and exit 1 as Python does on EPIPE.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(EXIT_FAILURE)
    sys.exit(code)


def _resolve(target: str) -> Callable[..., object]:
    module_name, _, function = target.partition(":")
    return cast(Callable[..., object], getattr(importlib.import_module(module_name), function))
