"""The figures of ``bench.json``: each with its value, the baseline measured in the same run,
its goal and whether it holds, built from the bench parts' raw results (:mod:`hil.benchmarks`
runs the parts; :func:`hil.bench_table.figure` is one figure's shape).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

from hil.bench_table import figure

# What ``python -m hil bench --only`` can select; every figure belongs to the part(s) it is
# built from.
PARTS = ("core", "publish", "soak", "start", "cli", "visca", "render", "depth", "replay")
# A long soak shorter than this is not quoted (the goal's RSS slope is measured over 30 minutes).
LONG_SOAK_MIN_S = 25 * 60.0
ROLES = ("track", "burst", "transit", "acquire")
CORE_MEAN_GOAL_MS = 0.5
CORE_P99_GOAL_MS = 1.5
CORE_RATIO_GOAL = 10.0
LATENCY_P50_GOAL_MS = 3.0
LATENCY_P99_GOAL_MS = 8.0
SERVICE_CPU_GOAL_PCT = 10.0
REPLAY_GOAL_FPS = 1000.0
FIRST_ESTIMATE_GOAL_S = 5.0
HELP_GOAL_S = 0.3
RSS_SLOPE_GOAL_MIB_H = 1.0
DEPTH_RATIO_GOAL = 0.95
ESTIMATE_RATE_HZ = 30.0


def figures_from(raw: dict[str, Any], parts: Collection[str] = PARTS) -> list[dict[str, Any]]:
    """Every figure from the components' raw results (a missing component gives None values);
    only the figures of ``parts`` (:data:`PARTS`)."""
    part = {
        k: raw.get(k) or {}
        for k in (
            "soak", "soak_fresh", "soak_long", "bench_publish", "bench_core", "replay",
            "bench_cli", "depth_rate", "bench_visca", "bench_render", "bench_start",
        )
    }  # fmt: skip
    # Built only for the parts run (a part not run holds {"skipped": …}, not its results).
    groups: list[tuple[set[str], Callable[[], list[dict[str, Any]]]]] = [
        ({"soak", "publish"}, lambda: _latency_figures(part["soak"], part["bench_publish"])),
        ({"core"}, lambda: _core_figures(part["bench_core"])),
        ({"soak"}, lambda: _service_figures(part["soak"], part["soak_fresh"])),
        ({"soak"}, lambda: _memory_figures(part["soak"], part["soak_long"])),
        ({"start"}, lambda: _start_figures(part["bench_start"])),
        ({"replay"}, lambda: _replay_figures(part["replay"])),
        ({"cli"}, lambda: _help_figures(part["bench_cli"])),
        ({"depth"}, lambda: _depth_figures(part["depth_rate"])),
        ({"visca", "render"}, lambda: _other_figures(part["bench_visca"], part["bench_render"])),
    ]
    return [f for owners, build in groups if owners & set(parts) for f in build()]


# -- private -------------------------------------------------------------------------------------


def _latency_figures(soak: dict[str, Any], publish: dict[str, Any]) -> list[dict[str, Any]]:
    lat = soak.get("latency_ms", {})
    own = lat.get("delivered_to_subscriber", {})
    rate = soak.get("estimate_hz")
    floor = publish.get("floor", {})
    path = publish.get("path", {})
    at = "–" if rate is None else f"{rate:.1f}"
    out = []
    for q, goal in (("p50", LATENCY_P50_GOAL_MS), ("p99", LATENCY_P99_GOAL_MS)):
        value = own.get(q)
        out.append(
            figure(
                f"latency_{q}",
                f"frame delivered → MQTT subscriber {q} (live daemon, {at} estimates/s)",
                value,
                "ms",
                f"≤ {goal:g} ms at {ESTIMATE_RATE_HZ:g} estimates/s",
                baseline=f"bare MQTT publish → subscriber {q} (same broker)",
                baseline_value=floor.get(f"{q}_ms"),
                ok=None if value is None else value <= goal,
            )
        )
    for q, goal in (("p50", LATENCY_P50_GOAL_MS), ("p99", LATENCY_P99_GOAL_MS)):
        value = path.get(f"{q}_ms")
        out.append(
            figure(
                f"publish_path_{q}",
                f"core output → MQTT subscriber {q} (publish path at "
                f"{publish.get('rate_hz', ESTIMATE_RATE_HZ):g}/s)",
                value,
                "ms",
                f"≤ {goal:g} ms",
                baseline=f"bare MQTT publish → subscriber {q}",
                baseline_value=floor.get(f"{q}_ms"),
                ok=None if value is None else value <= goal,
            )
        )
    e2s = lat.get("exposure_to_subscriber", {}).get("p50")
    out.append(
        figure(
            "exposure_p50",
            "exposure → MQTT subscriber p50 (live daemon, simulated capture included)",
            e2s,
            "ms",
            "reported (the capture's own latency is not the service's)",
            baseline="nominal simulated capture lag: exposure/2 + 1 frame, ms",
            baseline_value=lat.get("sim_delivery_lag_ms"),
        )
    )
    return out


def _core_figures(core: dict[str, Any]) -> list[dict[str, Any]]:
    by_role = core.get("core_by_role", {})
    tuned = core.get("baseline_tuned_full_frame", {}).get("mean_ms")
    # The core users run: the pipeline and the service's 3D trackers (bench_core times exactly
    # that; results written before it named them timed the same core).
    what = "+".join(core.get("trackers") or ("mmae",))
    out = []
    for role in ROLES:
        s = by_role.get(role, {})
        for stat, goal in (("mean", CORE_MEAN_GOAL_MS), ("p99", CORE_P99_GOAL_MS)):
            value = s.get(f"{stat}_ms")
            out.append(
                figure(
                    f"core_{role}_{stat}",
                    f"service core CPU (pipeline + {what} 3D tracker) per {role} frame, {stat} "
                    f"(n {s.get('n', 0)})",
                    value,
                    "ms",
                    f"≤ {goal:g} ms",
                    baseline="tuned OpenCV full-frame pipeline, mean",
                    baseline_value=tuned,
                    ok=None if value is None else value <= goal,
                )
            )
    track = by_role.get("track", {}).get("mean_ms")
    ratio = tuned / track if tuned and track else None
    naive = core.get("baseline_naive_full_frame", {}).get("mean_ms")
    out.append(
        figure(
            "core_vs_tuned",
            f"tuned OpenCV full-frame time / service core time (pipeline + {what} 3D tracker) "
            "per tracking frame",
            ratio,
            "×",
            f"≥ {CORE_RATIO_GOAL:g}×",
            baseline="tuned OpenCV full-frame pipeline, mean ms",
            baseline_value=tuned,
            ok=None if ratio is None else ratio >= CORE_RATIO_GOAL,
        )
    )
    out.append(
        figure(
            "core_vs_naive",
            "naive float64 full-frame time / core time per tracking frame",
            naive / track if naive and track else None,
            "×",
            "reported (the tuned ratio is the goal)",
            baseline="naive NumPy full-frame pipeline, mean ms",
            baseline_value=naive,
        )
    )
    return out


def _service_figures(soak: dict[str, Any], fresh: dict[str, Any]) -> list[dict[str, Any]]:
    cpu = soak.get("service_cpu_pct_one_core")
    rate = soak.get("estimate_hz")
    warm = soak.get("start_to_first_estimate_s")
    cold = fresh.get("start_to_first_estimate_s")
    at = "–" if rate is None else f"{rate:.1f}"
    return [
        figure(
            "service_cpu",
            f"service CPU without the simulator (live daemon, {at} estimates/s)",
            cpu,
            "% of a core",
            f"≤ {SERVICE_CPU_GOAL_PCT:g} % at 30 fps, an estimate on every frame",
            baseline="the whole process with the simulator's threads",
            baseline_value=soak.get("cpu_pct_one_core"),
            ok=None if cpu is None else cpu <= SERVICE_CPU_GOAL_PCT,
        ),
        figure(
            "first_estimate_warm",
            "start → first estimate, kernels compiled ahead (python -m dffd.warmup)",
            warm,
            "s",
            f"≤ {FIRST_ESTIMATE_GOAL_S:g} s",
            baseline="the same start with an empty kernel cache",
            baseline_value=cold,
            ok=None if warm is None else warm <= FIRST_ESTIMATE_GOAL_S,
        ),
        figure(
            "first_estimate_fresh",
            "start → first estimate, empty kernel cache (NumPy kernels while numba compiles)",
            cold,
            "s",
            f"≤ {FIRST_ESTIMATE_GOAL_S:g} s",
            baseline="the same start with the kernels compiled ahead",
            baseline_value=warm,
            ok=None if cold is None else cold <= FIRST_ESTIMATE_GOAL_S,
        ),
    ]


def _memory_figures(soak: dict[str, Any], long: dict[str, Any]) -> list[dict[str, Any]]:
    """The RSS slope of the long soak (the goal's measurement) and of the bench's own run."""
    goal = f"< {RSS_SLOPE_GOAL_MIB_H:g} MiB/h over 30 minutes"
    rss = soak.get("rss_mib", {})
    slope = rss.get("slope_mib_per_hour")
    short = (
        f"resident memory slope, the bench's {soak.get('run_s', 0):.0f} s run (least squares "
        f"after {rss.get('slope_from_s', 0):.0f} s; RSS still settling)"
    )
    long_rss = long.get("rss_mib", {})
    long_slope = long_rss.get("slope_mib_per_hour")
    if long_slope is None or float(long.get("run_s") or 0.0) < LONG_SOAK_MIN_S:
        # No long soak to quote: the short run is the only figure, and it carries the verdict.
        return [
            figure(
                "rss_slope",
                short,
                slope,
                "MiB/h",
                goal,
                baseline="lowest RSS of the run, MiB",
                baseline_value=rss.get("min"),
                ok=None if slope is None else abs(slope) < RSS_SLOPE_GOAL_MIB_H,
            )
        ]
    rate = long.get("estimate_hz")
    return [
        figure(
            "rss_slope",
            f"resident memory slope, {float(long['run_s']) / 60:.0f}-minute soak "
            f"(`hil soak`, {long.get('file', 'long soak')}: commit {long.get('commit') or '?'}, "
            f"{long.get('t') or 'date unknown'}, {'–' if rate is None else f'{rate:.1f}'} "
            f"estimates/s; least squares after {float(long_rss.get('slope_from_s') or 0):.0f} s)",
            long_slope,
            "MiB/h",
            goal,
            baseline="lowest RSS of that soak, MiB",
            baseline_value=long_rss.get("min"),
            ok=abs(long_slope) < RSS_SLOPE_GOAL_MIB_H,
        ),
        figure(
            "rss_slope_bench_run",
            short,
            slope,
            "MiB/h",
            "reported (the 30-minute soak above is the measurement)",
            baseline="lowest RSS of the run, MiB",
            baseline_value=rss.get("min"),
        ),
    ]


def _start_figures(start: dict[str, Any]) -> list[dict[str, Any]]:
    depth = start.get("median_first_depth_s")
    estimate = start.get("median_first_estimate_s")
    runs = start.get("runs", [])
    errors = [
        abs(r["first_depth_m"] - r["first_depth_truth_m"])
        for r in runs
        if r.get("first_depth_m") is not None and r.get("first_depth_truth_m") is not None
    ]
    worst = f"; first depth off by ≤ {max(errors):.2f} m" if errors else ""
    return [
        figure(
            "first_depth_warm",
            f"start → first depth (z_m not null) of `dffd run --no-console` on the embedded "
            f"default, kernels cached, median of {len(runs)} starts{worst}",
            depth,
            "s",
            f"≤ {FIRST_ESTIMATE_GOAL_S:g} s",
            baseline="start → first estimate of the same starts, s",
            baseline_value=estimate,
            ok=None if depth is None else depth <= FIRST_ESTIMATE_GOAL_S,
        )
    ]


def _replay_figures(replay: dict[str, Any]) -> list[dict[str, Any]]:
    fps = replay.get("replay_fps")
    bound = replay.get("cpu_bound_fps_2_cores")
    return [
        figure(
            "replay_cpu_bound_fps",
            "dffd replay frames/s its CPU per frame allows on 2 idle cores (calling thread "
            f"{_fmt(replay.get('main_thread_cpu_ms_per_frame'))} ms, process "
            f"{_fmt(replay.get('process_cpu_ms_per_frame'))} ms per frame)",
            bound,
            "frames/s",
            f"≥ {REPLAY_GOAL_FPS:g} frames/s (derived: the wall-time figure is the measurement)",
            baseline="PNG decoding alone, one thread, frames/s",
            baseline_value=replay.get("decode_one_thread_fps"),
            ok=None if bound is None else bound >= REPLAY_GOAL_FPS,
        ),
        figure(
            "replay_fps",
            f"dffd replay frames/s ({replay.get('frames', 0)} frames: decode, core, EST.jsonl)",
            fps,
            "frames/s",
            f"≥ {REPLAY_GOAL_FPS:g} frames/s on 2 cores",
            baseline="PNG decoding alone, one thread, frames/s",
            baseline_value=replay.get("decode_one_thread_fps"),
            ok=None if fps is None else fps >= REPLAY_GOAL_FPS,
        ),
    ]


def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _help_figures(cli: dict[str, Any]) -> list[dict[str, Any]]:
    base = cli.get("baseline_s")
    return [
        figure(
            "help_" + label.replace("dffd ", "").replace(" --help", "").replace("--help", "dffd"),
            f"`{label}` wall time",
            seconds,
            "s",
            f"≤ {HELP_GOAL_S:g} s",
            baseline="python -c pass",
            baseline_value=base,
            ok=seconds <= HELP_GOAL_S,
        )
        for label, seconds in cli.get("help_s", {}).items()
    ]


def _depth_figures(rates: dict[str, Any]) -> list[dict[str, Any]]:
    out = []
    for name, r in rates.items():
        limit = r.get("limit")
        hz = r.get("steady_depth_hz")
        ratio = hz / limit["depth_hz"] if limit and hz is not None else None
        parts = ""
        if limit:
            parts = (
                f"; limit: {limit['cycle_frames']} frames per depth, moves "
                f"{'/'.join(f'{s * 1e3:.0f}' for s in limit['move_s'])} ms = motor "
                f"{'/'.join(f'{s * 1e3:.0f}' for s in limit['motor_travel_s'])} + link "
                f"{limit['link_s_per_move'] * 1e3:.0f} ms"
            )
        out.append(
            figure(
                f"depth_ratio_{name}",
                f"depth measurements / limit, {name}{parts}",
                ratio,
                "of the limit",
                f"≥ {DEPTH_RATIO_GOAL:g}",
                baseline="limit from frame rate, motor and link timing, Hz",
                baseline_value=None if not limit else limit["depth_hz"],
                ok=None if ratio is None else ratio >= DEPTH_RATIO_GOAL,
            )
        )
    return out


def _other_figures(visca: dict[str, Any], render: dict[str, Any]) -> list[dict[str, Any]]:
    out = []
    unpaced = visca.get("unpaced", {}).get("command")
    if unpaced:
        out.append(
            figure(
                "visca_overhead",
                "VISCA driver overhead (unpaced round trip)",
                unpaced["median_ms"],
                "ms",
                "≪ the wire time (< 0.25×)",
                baseline="wire time at 9600 baud, ms",
                baseline_value=unpaced["wire_ms_at_9600"],
                ok=unpaced["ratio_to_wire"] < 0.25,
            )
        )
    overall = render.get("overall")
    if overall:
        budget = float(render.get("budget_ms", 5.0))
        out.append(
            figure(
                "sim_render_p95",
                "simulator render time per 640×480 frame, p95",
                overall["p95_ms"],
                "ms",
                f"≤ {budget:g} ms",
                baseline="budget, ms",
                baseline_value=budget,
                ok=overall["p95_ms"] <= budget,
            )
        )
    cpu = render.get("overall_cpu")
    if cpu:
        budget = float(render.get("budget_ms", 5.0))
        out.append(
            figure(
                "sim_render_cpu_p95",
                "simulator render CPU per 640×480 frame, p95 (the rendering thread's CPU time; "
                "the wall time above also holds the machine's other work)",
                cpu["p95_ms"],
                "ms",
                f"≤ {budget:g} ms",
                baseline="budget, ms",
                baseline_value=budget,
                ok=cpu["p95_ms"] <= budget,
            )
        )
    return out
