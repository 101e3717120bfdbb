"""Exit codes of every ``dffd`` subcommand (one meaning each; README.md lists them).

``drivers`` never imports :mod:`dffd`, so ``dffd sim-camera`` and ``dffd devices`` keep their own
constants of the same values; tests/test_cli.py holds them equal.
"""

from __future__ import annotations

from typing import Final

__all__ = ["EXIT_CODES_HELP", "EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE"]

EXIT_OK: Final = 0
# A runtime failure: the camera, broker or recording could not be used; the message says why.
# Also stdout's reader gone (`| head`): quietly, as Python exits on EPIPE (dffd.cli.entry_point).
EXIT_FAILURE: Final = 1
# Usage or configuration error: bad arguments, an invalid config, or a file or device the config
# names that does not exist (what `dffd check-config --check-files` reports, with this code).
EXIT_USAGE: Final = 2
# Interrupted by the user before start-up finished (128 + SIGINT, the shell's convention); also
# `dffd calibrate` stopped by the operator (Ctrl-C, or Ctrl-D at a prompt).
EXIT_INTERRUPTED: Final = 130

EXIT_CODES_HELP: Final = (
    "Exit codes: 0 ok, 1 runtime failure, 2 usage/config error, 130 interrupted."
)
