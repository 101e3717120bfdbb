"""The bench's depth-rate part: lock-step runs of every scenario, accepted depths per second
against the limit the configuration allows, with the limit's parts (motor travel, link, frames).

Run in ``python -m hil bench``'s own process (:mod:`hil.benchmarks`); its figures are built in
:mod:`hil.bench_figures`.
"""

from __future__ import annotations

import time
from typing import Any

# Lock-step depth-rate runs, per scenario (scenario seconds).
RATE_DURATION_S = 30.0
QUICK_RATE_DURATION_S = 8.0
RATE_SCENARIOS = ("static", "approach", "paper-circle", "figure-eight", "random")
QUICK_RATE_SCENARIOS = ("static",)


def depth_rates(quick: bool) -> dict[str, Any]:
    """Lock-step runs of every scenario: accepted depths/s against the configuration's limit."""
    from dffd.core.lens import Lens
    from dffd.scheduler.budget import depth_rate_limit, focus_move_time_s
    from dffd.scheduler.wire import COMPLETION_BYTES, FOCUS_DIRECT_BYTES, link_time_s
    from hil.lockstep import daemon_config, run_session, scheduler_config
    from hil.scenario import load_scenario
    from hil.simbuild import build_session

    duration = QUICK_RATE_DURATION_S if quick else RATE_DURATION_S
    out: dict[str, Any] = {}
    for name in QUICK_RATE_SCENARIOS if quick else RATE_SCENARIOS:
        scenario = load_scenario(name)
        case, traj = scenario.expand()[0]
        seed = scenario.seeds[0]
        t0 = time.perf_counter()
        res = run_session(scenario, case, traj, seed, duration_s=duration)
        wall = time.perf_counter() - t0
        spacing = res.extra.get("median_burst_half_span_counts")
        entry: dict[str, Any] = {
            "case": case,
            "duration_s": res.duration_s,
            "wall_s": wall,
            "accepted": res.accepted_bursts,
            "bursts": len(res.bursts),
            "depth_hz": res.depth_hz,
        }
        if spacing is not None:
            session = build_session(scenario, traj, seed)
            cfg = scheduler_config(
                session, Lens.from_toml(session.lens_path), daemon_config(), scenario.scheduler
            )
            low, high = res.extra.get("median_burst_sides_counts") or (spacing, spacing)
            limit = depth_rate_limit(cfg, (low, high))
            link = (
                link_time_s(FOCUS_DIRECT_BYTES, cfg.baudrate)
                + cfg.command_slot_s
                + link_time_s(COMPLETION_BYTES, cfg.baudrate)
            )
            moves = (low, low + high, high) if cfg.burst_mode != "rolling" else (low, high)
            entry["limit"] = {
                "depth_hz": limit.depth_hz,
                "cycle_frames": limit.cycle_frames,
                "frame_period_s": cfg.period_s,
                "exposure_and_guards_s": cfg.exposure + 2.0 * cfg.guard_s,
                "burst_half_span_counts": spacing,
                # the bracket's sides (middle − low end, high end − middle), medians
                "burst_sides_counts": [low, high],
                "moves_counts": list(moves),
                "motor_travel_s": [abs(d) / cfg.focus_speed_counts_per_s for d in moves],
                "link_s_per_move": link,
                "move_s": [focus_move_time_s(cfg, d) for d in moves],
                "move_frames": list(limit.move_frames),
                "tracking_frames": cfg.burst_every_frames,
                "burst_mode": cfg.burst_mode,
                "baudrate": cfg.baudrate,
            }
            # From the first burst on: the acquisition before it is not a scheduling loss.
            first = min((b.t for b in res.bursts), default=None)
            if first is not None and res.duration_s > first:
                steady = sum(1 for b in res.bursts if b.accepted) / (res.duration_s - first)
                entry["steady_depth_hz"] = steady
        out[name] = entry
    return out
