"""``python -m hil bench``: every performance figure of issue 15, each against its baseline.

Each figure in ``bench.json`` has a value, the baseline it is compared against **measured in the
same run**, its goal and whether it holds. The component benchmarks run in their own processes
(timings do not interfere):

* ``hil.bench_core`` — core CPU per frame for every role (track, burst, transit, acquire), mean
  and p99, against the tuned OpenCV full-frame baseline on the same frames (ratio ≥ 10×);
* ``hil.bench_publish`` — core output → MQTT subscriber at 30 messages/s through the daemon's
  hand-off, payload conversion and publisher, against a bare MQTT client's floor;
* ``hil soak`` (the live daemon on the simulator) — frame delivered → subscriber latency (the
  service's own share, matched per frame through ``…/sim/truth``) at the daemon's estimate
  rate, service CPU without the simulator's render thread, start → first estimate with the
  kernels compiled ahead; a second, short start with an empty kernel cache;
* the RSS slope is the goal's own measurement, a 30-minute soak: the bench quotes the latest
  one committed (:data:`LONG_SOAK_FILE`, with its date, commit, length and estimate rate in the
  figure's name) and reports its own 2-minute run's slope beside it, without a verdict (RSS
  settles over the first minutes: bounded histories and caches filling);
* ``hil.bench_cli`` — every ``dffd … --help`` against a bare interpreter start;
* ``hil.bench_start`` — start → first depth of ``dffd run`` on its embedded default (the broker
  and dashboard ports moved), against start → first estimate of the same starts;
* ``hil.bench_visca`` and ``hil.bench_render`` — serial round trip, simulator render time;

and in this process: depth measurements per second against the limit the configuration allows
(with the limit's parts: motor travel, link, frames) on every scenario, and ``dffd replay``'s
frames/s on a recording made here, against PNG decoding alone.

``python -m hil bench --readme [README.md]`` rewrites the README's performance table from
``OUT/bench.json`` (:mod:`hil.bench_table`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

from hil.bench_table import figure, write_readme
from hil.soak import git_commit

__all__ = ["BENCH_SCHEMA", "PARTS", "figures_from", "run_bench", "write_readme"]

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
BENCH_SCHEMA = 2
# One component may take this long (the fresh-cache start compiles ~25 s of kernels on a loaded
# 2-core machine; the soak runs SOAK_S plus start-up); a hung one is killed and reported.
COMPONENT_TIMEOUT_S = 600.0
# The live daemon's measured run: long enough for a few thousand estimates.
SOAK_S = 120.0
# The latest long soak (`python -m hil soak --minutes 30 --out DIR`, DIR/soak.json copied here):
# the RSS slope the goal means, measured over 30 minutes. A shorter soak is not quoted.
LONG_SOAK_FILE = REPO_ROOT / "docs" / "soak-30min.json"
LONG_SOAK_MIN_S = 25 * 60.0
QUICK_SOAK_S = 12.0
# Lock-step depth-rate runs, per scenario (scenario seconds).
RATE_DURATION_S = 30.0
QUICK_RATE_DURATION_S = 8.0
RATE_SCENARIOS = ("static", "approach", "paper-circle", "figure-eight", "random")
QUICK_RATE_SCENARIOS = ("static",)
# The replay recording: a static target at 4 m.
REPLAY_SCENARIO = "static"
REPLAY_CASE = "z4m"
REPLAY_DURATION_S = 30.0
QUICK_REPLAY_DURATION_S = 6.0
# Frames re-encoded in each PNG encoding to compare their decoding cost.
DECODE_SAMPLE_FRAMES = 200
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
# What ``python -m hil bench --only`` can select, and the part each component process is in.
PARTS = ("core", "publish", "soak", "start", "cli", "visca", "render", "depth", "replay")
_COMPONENT_PART = {
    "bench_core": "core",
    "bench_publish": "publish",
    "bench_cli": "cli",
    "bench_visca": "visca",
    "bench_render": "render",
    "bench_start": "start",
}


def run_bench(out_dir: Path, *, quick: bool = False, only: Sequence[str] | None = None) -> int:
    """Run every benchmark (or the ``only`` parts of :data:`PARTS`), print the figures and
    write ``out_dir/bench.json`` (a partial run says which parts it holds under ``only``)."""
    unknown = sorted(set(only or ()) - set(PARTS))
    if unknown:
        raise ValueError(f"unknown bench part(s) {unknown}: choose from {', '.join(PARTS)}")
    parts = set(only) if only else set(PARTS)
    out_dir.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    soak_s = QUICK_SOAK_S if quick else SOAK_S
    components: dict[str, list[str]] = {
        "bench_core": ["--frames", "150" if quick else "900"],
        "bench_publish": ["--messages", "90" if quick else "900"],
        "bench_cli": ["--repeat", "2" if quick else "5"],
        "bench_visca": ["--n", "20" if quick else "200"],
        "bench_render": ["--frames", "30" if quick else "300"],
        "bench_start": ["--repeat", "1" if quick else "3"],
    }
    raw: dict[str, Any] = {}
    skipped = {"skipped": "not in --only"}
    for name, args in components.items():
        if _COMPONENT_PART[name] not in parts:
            raw[name] = skipped
            continue
        raw[name] = _component(f"hil.{name}", [*args, "--out", str(out_dir / f"{name}.json")])
    raw["soak"] = _soak(out_dir / "soak", soak_s, fresh=False) if "soak" in parts else skipped
    # The empty-cache start compiles every kernel (~15-25 s): the full run only.
    if "soak" not in parts:
        raw["soak_fresh"] = skipped
    else:
        raw["soak_fresh"] = (
            {"skipped": "--quick"} if quick else _soak(out_dir / "soak-fresh", 1.0, fresh=True)
        )
    raw["soak_long"] = _long_soak(LONG_SOAK_FILE) if "soak" in parts else skipped
    raw["depth_rate"] = _depth_rates(quick) if "depth" in parts else skipped
    raw["replay"] = _replay(quick) if "replay" in parts else skipped
    figures = figures_from(raw, parts)
    doc = {
        "schema": BENCH_SCHEMA,
        "quick": quick,
        "only": sorted(parts) if only else None,
        "t": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "commit": git_commit(),
        # Other work on the machine slows every figure; the 1/5/15-minute load averages say how
        # much there was (2 cores: above 2 the bench shared them).
        "load_average": {"before": list(load_before), "after": list(os.getloadavg())},
        "figures": figures,
        "raw": raw,
    }
    path = out_dir / "bench.json"
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n", encoding="utf-8")
    for f in figures:
        verdict = {True: "PASS", False: "FAIL", None: "  - "}[f["ok"]]
        base = (
            "" if f["baseline_value"] is None else f" vs {f['baseline']} {f['baseline_value']:.4g}"
        )
        shown = "–" if f["value"] is None else f"{f['value']:.4g}"
        print(f"[{verdict}] {f['name']}: {shown} {f['unit']}{base}  (goal {f['goal']})")
    print(f"bench: {path}")
    return 0


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


# -- components (subprocesses) ---------------------------------------------------------------


def _component(module: str, args: list[str], *, out: Path | None = None) -> dict[str, Any]:
    """Run ``python -m module args``; its JSON result (``--out`` in ``args`` or ``out``)."""
    if importlib.util.find_spec(module) is None:
        return {"missing": f"{module} is not in this tree"}
    result = out if out is not None else Path(args[args.index("--out") + 1])
    cmd = [sys.executable, "-m", module, *args]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(  # noqa: S603 - this repository's own module
            cmd,
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=COMPONENT_TIMEOUT_S,
            check=False,
        )
    except subprocess.TimeoutExpired:
        return {"error": f"{module} did not finish within {COMPONENT_TIMEOUT_S:.0f} s"}
    if not result.exists():
        tail = (proc.stderr or proc.stdout)[-2000:]
        return {"error": f"{module} exited {proc.returncode} without results: {tail}"}
    data: dict[str, Any] = json.loads(result.read_text(encoding="utf-8"))
    data["_wall_s"] = time.perf_counter() - t0
    data["_exit"] = proc.returncode
    return data


def _long_soak(path: Path) -> dict[str, Any]:
    """The summary of the committed long soak (its series left out), or why there is none."""
    try:
        doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return {"missing": f"{path}: {exc}"}
    return {k: v for k, v in doc.items() if k not in ("rss_series", "windows")} | {
        "file": str(path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path)
    }


def _soak(out: Path, seconds: float, *, fresh: bool) -> dict[str, Any]:
    args = ["soak", "--seconds", f"{seconds:g}", "--out", str(out)]
    if fresh:
        args.append("--fresh-kernel-cache")
    return _component("hil", args, out=out / "soak.json")


# -- in-process measurements -----------------------------------------------------------------


def _depth_rates(quick: bool) -> dict[str, Any]:
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


def _replay(quick: bool) -> dict[str, Any]:
    """Record a lock-step session, then time ``dffd replay`` on it and PNG decoding alone."""
    import cv2

    from dffd.core.lens import Lens
    from dffd.recording import RecordingReader, RecordingWriter
    from dffd.replay import run as replay_cli
    from hil.lockstep import run_session
    from hil.runner import RecordingSink
    from hil.scenario import load_scenario
    from hil.simbuild import build_session

    duration = QUICK_REPLAY_DURATION_S if quick else REPLAY_DURATION_S
    scenario = load_scenario(REPLAY_SCENARIO)
    traj = dict(scenario.expand())[REPLAY_CASE]
    seed = scenario.seeds[0]
    session = build_session(scenario, traj, seed)
    lens = Lens.from_toml(session.lens_path)
    with tempfile.TemporaryDirectory(prefix="hil-bench-replay-") as tmp:
        rec = Path(tmp) / "rec"
        t0 = time.perf_counter()
        with RecordingWriter(rec, session.fps, session.frame_size, lens.to_meta()) as writer:
            run_session(
                scenario,
                REPLAY_CASE,
                traj,
                seed,
                duration_s=duration,
                recorder=RecordingSink(writer),
            )
        record_s = time.perf_counter() - t0
        reader = RecordingReader(rec)
        n = len(reader)
        png_bytes = sum((rec / r.file).stat().st_size for r in reader.records)
        t0 = time.perf_counter()
        for r in reader.records:
            cv2.imread(str(rec / r.file), cv2.IMREAD_UNCHANGED)
        decode_s = time.perf_counter() - t0
        encodings = _decode_cost(rec, reader.records[:DECODE_SAMPLE_FRAMES])
        args = argparse.Namespace(
            run=rec, out=Path(tmp) / "est.jsonl", config=None, summary=None, plot=None,
            roi=None, settle=None, known_size=None, best=None,
        )  # fmt: skip
        t0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
        code = replay_cli(args)
        replay_s = time.perf_counter() - t0
        main_cpu, all_cpu = time.thread_time() - c0, time.process_time() - p0
    return {
        "what": f"{REPLAY_SCENARIO}/{REPLAY_CASE}, {duration:g} s lock-step recording",
        "frames": n,
        "png_mib": png_bytes / 2**20,
        "record_s": record_s,
        "decode_one_thread_s": decode_s,
        "decode_one_thread_fps": n / decode_s if decode_s > 0 else None,
        "replay_s": replay_s,
        "replay_fps": n / replay_s if replay_s > 0 else None,
        # The core runs in the calling thread, decoding in a pool beside it: on 2 idle cores the
        # rate is bound by the calling thread's CPU per frame or by half the process's.
        "main_thread_cpu_ms_per_frame": 1e3 * main_cpu / n if n else None,
        "process_cpu_ms_per_frame": 1e3 * all_cpu / n if n else None,
        "cpu_bound_fps_2_cores": n / max(main_cpu, all_cpu / 2.0) if n and all_cpu > 0 else None,
        "replay_exit": code,
        "png_encodings": encodings,
    }


def _decode_cost(rec: Path, records: list[Any]) -> dict[str, Any]:
    """CPU per frame to decode and encode the same frames in each PNG encoding (from memory)."""
    import cv2
    import numpy as np

    from dffd.recording import PNG_PARAMS

    read = (cv2.imread(str(rec / r.file), cv2.IMREAD_UNCHANGED) for r in records)
    images = [im for im in read if im is not None]
    out: dict[str, Any] = {}
    for name, params in PNG_PARAMS.items():
        c0 = time.thread_time()
        blobs = [cv2.imencode(".png", im, list(params))[1] for im in images]
        encode = time.thread_time() - c0
        c0 = time.thread_time()
        for blob in blobs:
            cv2.imdecode(np.asarray(blob), cv2.IMREAD_UNCHANGED)
        decode = time.thread_time() - c0
        n = max(1, len(images))
        out[name] = {
            "frames": len(images),
            "kib_per_frame": sum(b.nbytes for b in blobs) / n / 1024,
            "decode_cpu_ms": 1e3 * decode / n,
            "encode_cpu_ms": 1e3 * encode / n,
        }
    return out


# -- figures ---------------------------------------------------------------------------------


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
