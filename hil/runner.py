"""``python -m hil run``: run a scenario's sessions, score them, write the report and plots."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from dffd.core.lens import Lens
from dffd.core.types import FrameTag
from dffd.recording import RecordingWriter
from drivers.frames import Frame
from drivers.sim.source import FrameTruth
from hil.report import build_report, format_table, write_plots, write_report
from hil.results import RunResult
from hil.scenario import Scenario

logger = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1


@dataclass(frozen=True, slots=True)
class RunOptions:
    """What ``python -m hil run`` was asked to do."""

    out_dir: Path
    fast: bool = True
    record: bool = False
    plots: bool = True
    baselines: bool = True
    progress: bool = True
    daemon_config: Path | None = None
    camera: str | None = None
    video: str | None = None
    truth_csv: Path | None = None


def run_scenario(scenario: Scenario, options: RunOptions) -> int:
    """Run every session of ``scenario``, write ``report.json`` and plots; print the table."""
    if options.fast:
        results = run_fast(scenario, options)
    else:
        from hil.realtime import run_realtime

        results = run_realtime(scenario, options)
    if not results:
        print("error: no session produced results")
        return EXIT_FAILURE
    thresholds = scenario.thresholds.model_dump()
    report = build_report(results, scenario.name, thresholds)
    report["overrides"] = {"scheduler": scenario.scheduler, "estimator": scenario.estimator}
    if options.camera is None:  # the simulator renders (not the lab's camera)
        from hil.simbuild import optics_model

        report["optics"] = optics_model(scenario)
    path = write_report(report, options.out_dir)
    if options.plots:
        plots = write_plots(results, options.out_dir)
        logger.info("wrote %d plots", len(plots))
    print(format_table(report))
    print(f"report: {path}")
    return EXIT_OK


def run_fast(scenario: Scenario, options: RunOptions) -> list[RunResult]:
    """Lock-step sessions: dffd on every case × seed, plus the baseline passes."""
    from hil.lockstep import run_session

    sessions = [(case, traj, seed) for case, traj in scenario.expand() for seed in scenario.seeds]
    pass_s = min(scenario.baselines.max_pass_s, scenario.duration_s)
    extra_passes = []
    if options.baselines and scenario.baselines.full_sweep:
        extra_passes.append("sweep")
    if options.baselines and scenario.baselines.aruco:
        extra_passes.append("aruco")
    total = len(sessions) * (scenario.duration_s + pass_s * len(extra_passes))
    results: list[RunResult] = []
    with _progress(options.progress, total, scenario.name) as advance:
        for case, traj, seed in sessions:
            with _recording(options, scenario, case, seed) as sink:
                res = run_session(
                    scenario,
                    case,
                    traj,
                    seed,
                    progress=advance(case, scenario.duration_s),
                    recorder=sink,
                )
            for policy in extra_passes:
                extra = run_session(
                    scenario,
                    case,
                    traj,
                    seed,
                    policy="sweep" if policy == "sweep" else "aruco",
                    duration_s=pass_s,
                    progress=advance(f"{case} {policy}", pass_s),
                )
                _merge_pass(res, extra, policy)
            results.append(res)
    return results


class RecordingSink:
    """Writes every frame of a lock-step session as a docs/design.md §8 recording."""

    def __init__(self, writer: RecordingWriter) -> None:
        self._writer = writer

    def add(self, frame: Frame, tag: FrameTag, truth: FrameTruth) -> None:
        """Store one frame with its tag and the truth: depth and camera-frame x, y, then the
        world-frame 3D truth (dffd.recording.TRUTH_COLUMNS)."""
        cam = truth.position_camera_m
        self._writer.write(
            frame,
            tag,
            (
                truth.z_m, cam[0], cam[1],
                *truth.position_world_m,
                *truth.velocity_world_mps,
                *truth.acceleration_world_mps2,
                truth.angular_speed_rad_s,
            ),
        )  # fmt: skip


def _merge_pass(res: RunResult, extra: RunResult, policy: str) -> None:
    if policy == "sweep":
        res.baselines["full_sweep"] = extra.baselines.get(
            "full_sweep", extra.baseline("full_sweep")
        )
        res.full_sweep_depth_hz = extra.full_sweep_depth_hz
        res.extra["full_sweep_pass"] = {
            "duration_s": extra.duration_s,
            "sweeps": len(extra.baselines.get("full_sweep", [])),
            "settings": extra.extra.get("sweep_settings"),
        }
    else:
        res.baselines["aruco"] = extra.baselines.get("aruco", extra.baseline("aruco"))
        res.extra["aruco_pass"] = extra.extra.get("aruco", {}) | {"duration_s": extra.duration_s}
        # dffd's own estimates on the ArUco card, for comparison on the very same frames.
        best = extra.estimates.get(extra.best)
        if best is not None and len(best):
            res.extra["aruco_pass"]["dffd_best_samples"] = len(best)
    res.notes.extend(n for n in extra.notes if n not in res.notes)


@contextmanager
def _recording(
    options: RunOptions, scenario: Scenario, case: str, seed: int
) -> Iterator[RecordingSink | None]:
    if not options.record:
        yield None
        return
    from hil.simbuild import build_session

    traj = dict(scenario.expand())[case]
    session = build_session(scenario, traj, seed)
    lens = Lens.from_toml(session.lens_path)
    name = case if len(scenario.seeds) == 1 else f"{case}-s{seed}"
    path = options.out_dir / "recording" / name
    writer = RecordingWriter(path, session.fps, session.frame_size, lens.to_meta())
    try:
        yield RecordingSink(writer)
    finally:
        writer.close()
        print(f"recording: {path}")


@contextmanager
def _progress(
    enabled: bool, total: float, title: str
) -> Iterator[Callable[[str, float], Callable[[float], None] | None]]:
    """``advance(label, seconds)`` returns a per-session callback (fraction done → bar)."""
    if not enabled:
        yield lambda _label, _seconds: None
        return
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} s of scenario"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task(title, total=total)
        done = 0.0

        def advance(label: str, seconds: float) -> Callable[[float], None]:
            nonlocal done
            base = done
            done += seconds

            def update(fraction: float) -> None:
                bar.update(
                    task, completed=base + fraction * seconds, description=f"{title}: {label}"
                )

            return update

        yield advance
        bar.update(task, completed=total)
