"""Render-time benchmark of the simulated camera (issue 3: ≤ 5 ms per 640×480 frame).

    python -m hil.bench_render [--frames N] [--config SIM_CAMERA.toml] [--out FILE]

Renders the reference camera in lock-step virtual time over cases that span the work the
renderer does: a small focused target (10 m), a large one (1.5 m), a heavily defocused one
(large PSF), a moving target with motion blur, and frames exposed while the focus motor turns.
Prints milliseconds per frame (mean, p50, p95, max) per case and overall, wall time and the
rendering thread's CPU time (the wall time also holds whatever else the machine ran meanwhile);
``--out`` writes the same figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from drivers.sim.config import (
    SimCameraConfig,
    TargetConfig,
    TrajectoryConfig,
    WorldConfig,
    load_sim_camera_config,
)
from drivers.sim.resources import reference_camera_file
from drivers.sim.rig import build_sim_camera
from drivers.sim.source import SimFrameSource
from drivers.sim.state import CameraState
from drivers.sim.virtual_clock import VirtualClock

BUDGET_MS = 5.0  # issue 3


Setup = Callable[[SimFrameSource, CameraState, VirtualClock], None]


def _focus(z: float) -> Setup:
    def setup(source: SimFrameSource, state: CameraState, clock: VirtualClock) -> None:
        state.focus.jump(source.optics.focus_counts_for_depth(z), clock())

    return setup


def _far(source: SimFrameSource, state: CameraState, clock: VirtualClock) -> None:
    state.focus.jump(source.optics.lens.focus_far_counts, clock())


def _sweeping(source: SimFrameSource, state: CameraState, clock: VirtualClock) -> None:
    state.focus.move_to(0x8000, speed=2000.0, t=clock())  # turns throughout the run


def _static(z: float) -> WorldConfig:
    return WorldConfig(trajectory=TrajectoryConfig(kind="static", position_m=(0.0, 0.0, z)))


CASES: dict[str, tuple[WorldConfig, Setup]] = {
    "focused-10m": (_static(10.0), _focus(10.0)),
    "focused-1.5m": (_static(1.5), _focus(1.5)),
    "defocused-1.5m": (_static(1.5), _far),  # blur radius ≈ 22 px
    "moving-2m/s-3m": (
        WorldConfig(
            trajectory=TrajectoryConfig(
                kind="linear", position_m=(-0.3, 0.0, 3.0), end_m=(0.3, 0.0, 3.0), speed_mps=2.0
            )
        ),
        _focus(3.0),
    ),
    "focus-transit-5m": (_static(5.0), _sweeping),
    "textured-3m": (
        WorldConfig(
            target=TargetConfig(shape="textured"),
            trajectory=TrajectoryConfig(kind="static", position_m=(0.0, 0.0, 3.0)),
        ),
        _focus(3.0),
    ),
}


def run_case(
    config: SimCameraConfig, world: WorldConfig, setup: Setup, frames: int
) -> tuple[list[float], list[float]]:
    """Render ``frames`` frames in lock-step; per-frame wall and thread-CPU times in ms."""
    rig = build_sim_camera(config.model_copy(update={"world": world}), virtual_start_s=0.0)
    clock, state, source = rig.virtual_clock, rig.state, rig.source
    setup(source, state, clock)
    source.render_frame(0)  # warm the PSF cache as a running camera would
    times, cpu = [], []
    for index in range(1, frames + 1):
        clock.set(source.delivery_time(index))
        start, c0 = time.perf_counter(), time.thread_time()
        source.render_frame(index)
        times.append(1e3 * (time.perf_counter() - start))
        cpu.append(1e3 * (time.thread_time() - c0))
    return times, cpu


def summarise(times: Sequence[float]) -> dict[str, float]:
    """Mean, median, 95th percentile and maximum."""
    ordered = sorted(times)
    return {
        "mean_ms": statistics.fmean(ordered),
        "p50_ms": ordered[len(ordered) // 2],
        "p95_ms": ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))],
        "max_ms": ordered[-1],
        "frames": float(len(ordered)),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; exit 0 when the mean over all cases is within the budget."""
    parser = argparse.ArgumentParser(prog="python -m hil.bench_render", description=__doc__)
    parser.add_argument("--frames", type=int, default=300, help="frames per case (default 300)")
    parser.add_argument("--config", type=Path, default=None)
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    args = parser.parse_args(argv)
    config = load_sim_camera_config(args.config or reference_camera_file())
    results: dict[str, dict[str, Any]] = {}
    all_times: list[float] = []
    all_cpu: list[float] = []
    for name, (world, setup) in CASES.items():
        times, cpu = run_case(config, world, setup, args.frames)
        all_times += times
        all_cpu += cpu
        results[name] = summarise(times) | {"cpu": summarise(cpu)}
        s, c = results[name], summarise(cpu)
        print(
            f"{name:18s} mean {s['mean_ms']:5.2f}  p50 {s['p50_ms']:5.2f}  "
            f"p95 {s['p95_ms']:5.2f}  max {s['max_ms']:6.2f} ms/frame  "
            f"(CPU mean {c['mean_ms']:5.2f}  p95 {c['p95_ms']:5.2f})"
        )
    overall = summarise(all_times)
    overall_cpu = summarise(all_cpu)
    print(
        f"{'all':18s} mean {overall['mean_ms']:5.2f}  p50 {overall['p50_ms']:5.2f}  "
        f"p95 {overall['p95_ms']:5.2f}  max {overall['max_ms']:6.2f} ms/frame  "
        f"(CPU mean {overall_cpu['mean_ms']:5.2f}  p95 {overall_cpu['p95_ms']:5.2f}; "
        f"budget {BUDGET_MS} ms, {config.sensor.width_px}×{config.sensor.height_px})"
    )
    if args.out:
        report = {
            "schema": 1,
            "frame_size": [config.sensor.width_px, config.sensor.height_px],
            "budget_ms": BUDGET_MS,
            "overall": overall,
            "overall_cpu": overall_cpu,
            "cases": results,
        }
        args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0 if overall["mean_ms"] <= BUDGET_MS else 1


if __name__ == "__main__":
    sys.exit(main())
