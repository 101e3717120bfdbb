"""Wall time of every ``dffd … --help`` against a bare interpreter start (issue 15).

Each command runs ``--repeat`` times in a fresh interpreter (``python -m dffd SUB --help``, what
the ``dffd`` script runs); the figure is the median wall time, the baseline the median of
``python -c pass`` measured in the same run, so the difference is what dffd's imports cost.

    python -m hil.bench_cli [--repeat 5] [--out bench_cli.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# A --help that takes longer than this is hung (the goal is 0.3 s; a cold disk cache ~2 s).
HELP_TIMEOUT_S = 30.0
GOAL_S = 0.3


def main(argv: Sequence[str] | None = None) -> int:
    """Time every ``--help``; print one line each; write JSON to ``--out``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per command (median)")
    parser.add_argument("--out", type=Path, default=None, help="JSON result file")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    result = measure(args.repeat)
    base = result["baseline_s"]
    for name, seconds in result["help_s"].items():
        verdict = "PASS" if seconds <= GOAL_S else "FAIL"
        print(f"[{verdict}] {name:<26s} {seconds:.3f} s (python -c pass {base:.3f} s)")
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")
    return 0


def measure(repeat: int) -> dict[str, Any]:
    """Median wall time of each ``--help`` and of a bare interpreter start."""
    from dffd.cli import SUBCOMMANDS

    commands: dict[str, list[str]] = {"dffd --help": []} | {
        f"dffd {name} --help": [name] for name in SUBCOMMANDS
    }
    baseline = _median_wall([sys.executable, "-c", "pass"], repeat)
    helps = {
        label: _median_wall([sys.executable, "-m", "dffd", *sub, "--help"], repeat)
        for label, sub in commands.items()
    }
    return {
        "what": "median wall time of a fresh interpreter running each command",
        "repeat": repeat,
        "baseline_s": baseline,
        "baseline": "python -c pass",
        "goal_s": GOAL_S,
        "help_s": helps,
    }


def _median_wall(cmd: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(  # noqa: S603 - this interpreter and this repository's CLI
            cmd, capture_output=True, timeout=HELP_TIMEOUT_S, check=True
        )
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


if __name__ == "__main__":
    sys.exit(main())
