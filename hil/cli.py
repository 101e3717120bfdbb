"""``python -m hil``: run a scenario, run the performance bench, or compare two reports.

Exit codes as ``dffd``: 0 ok, 1 runtime failure or (compare) a regression, 2 usage error.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

DEFAULT_OUT = Path("hil/out")

logger = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m hil``."""
    from hil.bench_figures import PARTS as BENCH_PARTS
    from hil.scenario import OPTICS_MODELS, SCENARIO_NAMES

    parser = argparse.ArgumentParser(
        prog="python -m hil",
        description="dffd hardware-in-the-loop bench: accuracy scenarios, performance, compare.",
        epilog="Exit codes: 0 ok, 1 failure or regression, 2 usage error.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    run = sub.add_parser(
        "run",
        help="run a scenario and write report.json + plots",
        description="Run a scenario. --fast: simulator, scheduler and core in lock-step "
        "virtual time. Default: the real daemon against the simulated camera over a pty, "
        "scored over MQTT. With --camera/--video/--truth: the real camera on the lab bench.",
    )
    run.add_argument(
        "scenario", help=f"scenario name ({', '.join(SCENARIO_NAMES)}) or a .toml path"
    )
    run.add_argument(
        "--out", type=Path, default=None, help="output directory (default hil/out/SCENARIO)"
    )
    run.add_argument("--fast", action="store_true", help="lock-step virtual time (no waiting)")
    run.add_argument(
        "--record",
        action="store_true",
        help="also write a recording (docs/design.md §8): one PNG per frame, ~555 MB per minute "
        "of scenario at 640x480 and 30 fps; the expected size and the free space are printed "
        "first, with a warning if the disk would fill within the hour",
    )
    run.add_argument(
        "--duration", type=float, default=None, help="override the per-case duration (s)"
    )
    run.add_argument("--seed", type=int, action="append", default=None, help="override the seeds")
    run.add_argument(
        "--seeds",
        default=None,
        metavar="S1,S2,...",
        help="override the seeds with a comma-separated list; the report adds mean and spread",
    )
    run.add_argument(
        "--optics",
        choices=OPTICS_MODELS,
        default=None,
        help="simulator optics model (default: the scenario's; aberrated: docs/estimation.md §8)",
    )
    run.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="experiment override: scheduler.KEY=V, estimator.KEY=V (dffd dataclass fields) or "
        "camera.SECTION.KEY=V (simulator config); recorded in report.json",
    )
    lens_table = run.add_mutually_exclusive_group()
    lens_table.add_argument(
        "--calibrate",
        action="store_true",
        help="fast mode (the default): tell the estimator the lens table `dffd calibrate --sim` "
        "fits on the session's camera, as the lab does; report.json gives its error "
        "(docs/estimation.md §10)",
    )
    lens_table.add_argument(
        "--simulator-table",
        action="store_true",
        help="diagnosis: score on the simulator's own (true) lens table, not a calibrated one",
    )
    run.add_argument(
        "--calibration-depths",
        default=None,
        metavar="Z1,Z2,...",
        help="target depths (m) of the calibration (default: dffd calibrate's, where the "
        "simulated target fits)",
    )
    run.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    run.add_argument("--no-baselines", action="store_true", help="skip the ArUco/full-sweep passes")
    run.add_argument("--config", type=Path, default=None, help="daemon config (real-time modes)")
    run.add_argument("--camera", default=None, help="lab: real camera, e.g. serial:/dev/ttyUSB0")
    run.add_argument("--video", default=None, help="lab: video device, e.g. /dev/video0")
    run.add_argument("--truth", type=Path, default=None, help="lab: ground-truth CSV (t_s,z_m)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")

    bench = sub.add_parser(
        "bench",
        help="performance bench (docs/design.md §10): CPU, replay, depth rate, latency, serial",
    )
    bench.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    bench.add_argument("--quick", action="store_true", help="shorter runs (smoke test)")
    bench.add_argument(
        "--only",
        action="append",
        choices=BENCH_PARTS,
        default=None,
        metavar="PART",
        help=f"run only this part (repeatable): {', '.join(BENCH_PARTS)}; e.g. --only core "
        "for the core CPU figures (~1 min instead of the whole bench)",
    )
    bench.add_argument(
        "--readme",
        type=Path,
        nargs="?",
        const=Path("README.md"),
        default=None,
        help="only rewrite the README's performance table from OUT/bench.json (default README.md)",
    )

    soak = sub.add_parser(
        "soak", help="long run of the live daemon: RSS slope, CPU, latency and rates over time"
    )
    length = soak.add_mutually_exclusive_group(required=True)
    length.add_argument("--minutes", type=float, help="run length after the first estimate")
    length.add_argument("--seconds", type=float, help="run length in seconds (smoke tests)")
    soak.add_argument("--scenario", default="static", help="the daemon's built-in world")
    soak.add_argument("--window", type=float, default=0.0, help="seconds per window (0: auto)")
    soak.add_argument("--out", type=Path, default=DEFAULT_OUT / "soak", help="output directory")
    soak.add_argument(
        "--fresh-kernel-cache",
        action="store_true",
        help="start with an empty NUMBA_CACHE_DIR (a fresh install without the kernel warm-up)",
    )
    soak.add_argument(
        "--probe",
        type=int,
        default=None,
        metavar="DEPTH",
        help="memory probe inside the daemon (hil.memprobe): RssAnon, glibc heap (mallinfo2), "
        "and with DEPTH > 0 tracemalloc at that traceback depth (slows the daemon)",
    )
    soak.add_argument(
        "--daemon-env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra environment for the daemon (A/B runs, e.g. GLIBC_TUNABLES=...); repeatable",
    )

    table = sub.add_parser("table", help="print reports as the README's markdown results table")
    table.add_argument("reports", type=Path, nargs="+", help="report.json files or directories")
    table.add_argument(
        "--accuracy",
        action="store_true",
        help="issue 11's accuracy table: best ss RMS, raw z_m, ratio, coverage, estimate rate, "
        "focus slope",
    )

    compare = sub.add_parser("compare", help="compare two reports; exit 1 on a regression")
    compare.add_argument("a", type=Path, help="reference report.json (or its directory)")
    compare.add_argument("b", type=Path, help="new report.json (or its directory)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run; return the exit code."""
    parser = build_parser()
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "compare":
            from hil.compare import main as compare_main

            return compare_main(args.a, args.b)
        if args.command == "table":
            from hil.report import load_report
            from hil.report_tables import accuracy_table, markdown_table

            loaded = [load_report(p) for p in args.reports]
            print(accuracy_table(loaded) if args.accuracy else markdown_table(loaded))
            return EXIT_OK
        if args.command == "bench":
            from hil.benchmarks import run_bench, write_readme

            if args.readme is not None:
                return write_readme(args.out / "bench.json", args.readme)
            return run_bench(args.out, quick=args.quick, only=args.only)
        if args.command == "soak":
            from hil.soak import run_soak

            seconds = args.seconds if args.seconds is not None else 60.0 * args.minutes
            return run_soak(
                seconds,
                args.out,
                args.scenario,
                args.window,
                fresh_kernel_cache=args.fresh_kernel_cache,
                probe=args.probe,
                daemon_env=dict(kv.split("=", 1) for kv in args.daemon_env),
            )
        return _run(args)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except ValueError as exc:  # scenario/report/config errors carry a user-facing message
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE


def parse_seeds(text: str | None) -> list[int]:
    """``"1,2,3"`` → ``[1, 2, 3]`` (None or empty: no seeds); ValueError says what was wrong."""
    if not text:
        return []
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ValueError(
            f"--seeds {text!r}: expected comma-separated integers, e.g. --seeds 1,2,3"
        ) from None


def _run(args: argparse.Namespace) -> int:
    from hil.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    if args.duration is not None:
        scenario = scenario.shortened(args.duration)
    seeds = [*(args.seed or []), *parse_seeds(args.seeds)]
    if seeds:
        scenario = scenario.model_copy(update={"seeds": tuple(dict.fromkeys(seeds))})
    if args.optics is not None:
        scenario = scenario.with_optics(args.optics)
    if args.settings:
        scenario = scenario.with_settings(args.settings)
    out = args.out or DEFAULT_OUT / scenario.name
    lab = any(x is not None for x in (args.camera, args.video, args.truth))
    if lab and args.fast:
        print("error: --fast runs the simulator; drop --camera/--video/--truth", file=sys.stderr)
        return EXIT_USAGE
    if lab and (args.camera is None or args.video is None):
        print(
            "error: the lab mode needs both --camera serial:PORT and --video DEV", file=sys.stderr
        )
        return EXIT_USAGE
    depths = None
    if args.calibration_depths is not None:
        try:
            depths = tuple(float(z) for z in args.calibration_depths.split(",") if z.strip())
        except ValueError:
            print(
                f"error: --calibration-depths {args.calibration_depths!r} is not a list of "
                "numbers (metres, comma-separated)",
                file=sys.stderr,
            )
            return EXIT_USAGE
    from hil.runner import RunOptions, run_scenario

    options = RunOptions(
        out_dir=out,
        fast=args.fast,
        record=args.record,
        plots=not args.no_plots,
        baselines=not args.no_baselines,
        progress=not args.no_progress,
        daemon_config=args.config,
        camera=args.camera,
        video=args.video,
        truth_csv=args.truth,
        calibrate=not args.simulator_table,
        calibration_depths=depths,
    )
    return run_scenario(scenario, options)
