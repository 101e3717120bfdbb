"""``python -m hil run``: run a scenario's sessions, score them, write the report and plots."""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from dffd.core.lens import Lens
from dffd.core.types import FrameTag
from dffd.recording import RecordingWriter
from drivers.frames import Frame
from drivers.sim.source import FrameTruth
from hil.calibration import Calibration, calibrated_lens
from hil.report import build_report, write_report
from hil.report_plots import write_plots
from hil.report_tables import format_table
from hil.results import RunResult
from hil.scenario import Scenario

logger = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1

# PNG size of the simulator's frames against their raw bytes. Recordings are written as stored
# PNG (dffd.recording.PNG_PARAMS "fast": no deflate, no row filter), so a frame is its raw bytes
# and a few headers: 555 MB per minute of scenario measured against 553 MB raw (approach,
# 640x480 gray). (OpenCV's default encoding, "small", gave 0.46-0.48 on the sensor noise.) An
# estimate for the up-front message, said as such.
PNG_FRACTION = 1.0
# Warn when the free disk space would run out within this much recording.
DISK_HORIZON_S = 3600.0
BYTES_PER_MB = 1e6


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
    # the estimator's lens table: (default) fitted by `dffd calibrate --sim` on the session's
    # camera, as the lab does (hil/calibration.py, docs/estimation.md §10); False: the
    # simulator's ground truth / packaged table (diagnosis)
    calibrate: bool = True
    calibration_depths: tuple[float, ...] | None = None  # None: dffd calibrate's defaults


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
    calib = [c for r in results if (c := r.extra.get("calibration")) is not None]
    if calib:
        seen = {(c["optics"], c["seed"]): c for c in calib}
        report["calibration"] = {
            "method": "dffd calibrate --sim on the session's camera (hil/calibration.py)",
            "tables": list(seen.values()),
            "depth_err_rms_m_max": max(c["depth_err_rms_m"] for c in seen.values()),
        }
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
    from hil.lockstep import Policy, run_session

    sessions = [(case, traj, seed) for case, traj in scenario.expand() for seed in scenario.seeds]
    pass_s = min(scenario.baselines.max_pass_s, scenario.duration_s)
    extra_passes: list[Policy] = []
    if options.baselines and scenario.baselines.full_sweep:
        extra_passes.append("sweep")
    if options.baselines and scenario.baselines.coarse_fine:
        extra_passes.append("coarse_fine")
    if options.baselines and scenario.baselines.aruco:
        extra_passes.append("aruco")
    total = len(sessions) * (scenario.duration_s + pass_s * len(extra_passes))
    if options.record:
        _announce_recording(scenario, options.out_dir, len(sessions))
    results: list[RunResult] = []
    calibrations: dict[int, Calibration] = {}
    if options.calibrate and options.camera is None:
        for seed in scenario.seeds:
            calibrations[seed] = calibrated_lens(
                scenario, seed, options.out_dir / "calibration", options.calibration_depths
            )
    with _progress(options.progress, total, scenario.name) as advance:
        for case, traj, seed in sessions:
            calib = calibrations.get(seed)
            lens_path = None if calib is None else calib.lens_path
            with _recording(options, scenario, case, seed, lens_path) as sink:
                res = run_session(
                    scenario,
                    case,
                    traj,
                    seed,
                    progress=advance(case, scenario.duration_s),
                    recorder=sink,
                    lens_path=lens_path,
                )
            if calib is not None:
                res.extra["calibration"] = {
                    k: v for k, v in calib.report.items() if k != "per_depth"
                }
            for policy in extra_passes:
                extra = run_session(
                    scenario,
                    case,
                    traj,
                    seed,
                    policy=policy,
                    duration_s=pass_s,
                    progress=advance(f"{case} {policy}", pass_s),
                    lens_path=lens_path,
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
    elif policy == "coarse_fine":
        res.baselines["coarse_fine"] = extra.baselines.get(
            "coarse_fine", extra.baseline("coarse_fine")
        )
        res.extra["coarse_fine_pass"] = {
            "duration_s": extra.duration_s,
            "depths": len(extra.baselines.get("coarse_fine", [])),
            "depth_hz": extra.full_sweep_depth_hz,
            "frames_per_depth": extra.extra.get("sweep_settings"),
        }
    else:
        res.baselines["aruco"] = extra.baselines.get("aruco", extra.baseline("aruco"))
        res.extra["aruco_pass"] = extra.extra.get("aruco", {}) | {"duration_s": extra.duration_s}
        # dffd's own estimates on the ArUco card, for comparison on the very same frames.
        best = extra.estimates.get(extra.best)
        if best is not None and len(best):
            res.extra["aruco_pass"]["dffd_best_samples"] = len(best)
    res.notes.extend(n for n in extra.notes if n not in res.notes)


def recording_plan(
    frame_size: tuple[int, int],
    fps: float,
    seconds: float,
    free_bytes: int,
    channels: int = 1,
) -> tuple[str, str | None]:
    """What a recording of ``seconds`` will take (a line to print) and a warning (or None)
    when ``free_bytes`` would run out within :data:`DISK_HORIZON_S` of recording or before
    this run ends."""
    w, h = frame_size
    raw_per_s = w * h * channels * fps
    per_s = raw_per_s * PNG_FRACTION
    total = per_s * seconds
    plan = (
        f"recording {w}x{h} frames at {fps:g} fps as PNG: ~{per_s * 60 / BYTES_PER_MB:.0f} MB "
        f"per minute of scenario ({raw_per_s * 60 / BYTES_PER_MB:.0f} MB/min uncompressed); "
        f"this run ~{total / BYTES_PER_MB:.0f} MB; {free_bytes / BYTES_PER_MB:.0f} MB free"
    )
    lasts_s = free_bytes / per_s if per_s > 0 else float("inf")
    if total > free_bytes:
        return plan, (
            f"warning: this run's recording (~{total / BYTES_PER_MB:.0f} MB) does not fit in "
            f"the {free_bytes / BYTES_PER_MB:.0f} MB free: the disk fills after ~"
            f"{lasts_s / 60:.0f} min of scenario; shorten it (--duration) or record elsewhere "
            "(--out)"
        )
    if lasts_s < DISK_HORIZON_S:
        return plan, (
            f"warning: at this rate the {free_bytes / BYTES_PER_MB:.0f} MB free last only "
            f"~{lasts_s / 60:.0f} min of recording"
        )
    return plan, None


def _announce_recording(scenario: Scenario, out_dir: Path, sessions: int) -> None:
    from hil.simbuild import build_session

    _case, traj = scenario.expand()[0]
    session = build_session(scenario, traj, scenario.seeds[0])
    plan, warning = recording_plan(
        session.frame_size,
        session.fps,
        sessions * scenario.duration_s,
        shutil.disk_usage(_existing_parent(out_dir)).free,
    )
    print(f"{plan} ({sessions} session(s) x {scenario.duration_s:g} s into {out_dir})")
    if warning is not None:
        print(warning)


def _existing_parent(path: Path) -> Path:
    path = path.resolve()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _recorded(path: Path) -> str:
    """What was written to the recording at ``path``: frames, MB, MB per minute."""
    frames = sorted((path / "frames").glob("*.png"))
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    text = f"{len(frames)} frames, {size / BYTES_PER_MB:.0f} MB"
    meta = path / "meta.json"
    if frames and meta.exists():
        fps = float(json.loads(meta.read_text(encoding="utf-8"))["fps"])
        text += f", {size / (len(frames) / fps) * 60 / BYTES_PER_MB:.0f} MB per minute"
    return text


@contextmanager
def _recording(
    options: RunOptions, scenario: Scenario, case: str, seed: int, lens_path: Path | None
) -> Iterator[RecordingSink | None]:
    if not options.record:
        yield None
        return
    from hil.simbuild import build_session

    traj = dict(scenario.expand())[case]
    session = build_session(scenario, traj, seed, lens_path=lens_path)
    lens = Lens.from_toml(session.lens_path)
    name = case if len(scenario.seeds) == 1 else f"{case}-s{seed}"
    path = options.out_dir / "recording" / name
    writer = RecordingWriter(path, session.fps, session.frame_size, lens.to_meta())
    try:
        yield RecordingSink(writer)
    finally:
        writer.close()
        print(f"recording: {path} ({_recorded(path)})")


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
