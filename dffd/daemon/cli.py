"""``dffd run``: the command around one :class:`~dffd.daemon.app.Daemon` — its exit code.

The allocator's settings before anything allocates, the configuration (checked by :mod:`dffd.cli`
before the daemon's imports, or here), ``[log] level`` against the command line's ``-v``, the
console view only on a terminal, ``--sim-faults``, and the terminal's foreground process group
while an operator watches (:mod:`dffd.cli.terminal`, so Ctrl-C under ``make run`` stops dffd
alone). The daemon itself (tasks, start-up, shutdown) is :mod:`dffd.daemon.app`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys

from dffd.cli import service_log_level
from dffd.config import check_run_config
from dffd.daemon import allocator
from dffd.daemon.app import Daemon
from dffd.exitcodes import EXIT_OK, EXIT_USAGE

__all__ = ["run"]


def run(args: argparse.Namespace) -> int:
    """Run until SIGTERM/SIGINT (or ``--duration``); return the exit code."""
    allocator.configure()  # before the daemon's threads allocate (see dffd.daemon.allocator)
    config = getattr(args, "checked_config", None)  # dffd.cli checked it before these imports
    if config is None:
        checked = check_run_config(args.config)
        if isinstance(checked, str):
            print(checked, file=sys.stderr)
            return EXIT_USAGE
        config = checked
    # [log] level sets dffd's own loggers, unless the command line's -v/-vv asks for more
    verbose = getattr(args, "verbose", 0)  # dffd's top-level -v (absent: not from dffd.cli)
    logging.getLogger("dffd").setLevel(service_log_level(config.log.level, verbose))
    live = not args.no_console and sys.stdout.isatty()
    if not live and not logging.getLogger().isEnabledFor(logging.INFO):
        # Without a TTY the status lines are the console; make sure they are visible.
        logging.getLogger("dffd.daemon.console").setLevel(logging.INFO)
        logging.getLogger().setLevel(logging.INFO)
    from drivers.sim.faults import Faults, FaultSpecError

    try:
        faults = Faults(args.sim_faults) if args.sim_faults else None
    except FaultSpecError as exc:
        print(f"dffd run: --sim-faults: {exc}", file=sys.stderr)
        return EXIT_USAGE
    daemon = Daemon(config, live_console=live, duration_s=args.duration, sim_faults=faults)
    from dffd.cli.terminal import own_foreground

    # Only with the live view: an operator at the terminal (make run). A daemon a script or a
    # test starts without the view must leave the terminal's Ctrl-C to its parent.
    with own_foreground() if live else contextlib.nullcontext(enter_result=False):
        try:
            return asyncio.run(daemon.main())
        except KeyboardInterrupt:
            return EXIT_OK
