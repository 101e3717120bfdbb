"""``python -m hil bench``: the performance figures of design.md §10, each against its baseline.

Runs the component benchmarks other parts ship (each in its own process so timings do not
interfere) and adds what only the bench can measure:

* ``hil.bench_core``: estimator CPU per tracking frame vs the naive full-frame baseline;
* ``hil.bench_visca``: serial command round trip vs the wire time of its bytes;
* ``hil.bench_render``: simulator render time vs its 5 ms budget;
* ``hil.bench_daemon`` (when present): exposure → MQTT latency, rates, CPU, RSS; otherwise the
  bench's own real-time run of the daemon gives the latency;
* replay frames/s (``dffd.replay`` on a lock-step recording) vs the camera's frame rate;
* depth measurements/s in lock-step vs the scheduler's theoretical limit.

Prints one line per figure with its ratio and writes ``bench.json``.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
BENCH_SCHEMA = 1
# One component benchmark may take this long (render: 6 cases × 300 frames ≈ 10 s; daemon:
# DAEMON_BENCH_S of real time plus start-up); a hung one is killed and reported.
COMPONENT_TIMEOUT_S = 600.0
# The daemon benchmark's measured run (its own default is 300 s for the RSS-growth check; the
# bench uses 2 minutes so `python -m hil bench` stays a few minutes in all).
DAEMON_BENCH_S = 120
# Lock-step scenario for the depth rate and the replay recording: a static target at 4 m.
RATE_SCENARIO = "static"
RATE_CASE = "z4m"
RATE_DURATION_S = 30.0
QUICK_RATE_DURATION_S = 8.0


def run_bench(out_dir: Path, *, quick: bool = False) -> int:
    """Run every benchmark, print the figures and write ``out_dir/bench.json``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    raw: dict[str, Any] = {}
    figures: list[dict[str, Any]] = []
    frames = "60" if quick else "300"
    components = {
        "bench_core": ["--frames", frames],
        "bench_visca": ["--n", "20" if quick else "200"],
        "bench_render": ["--frames", "30" if quick else "300"],
        "bench_daemon": ["--seconds", "10" if quick else str(DAEMON_BENCH_S)],
    }
    for name, args in components.items():
        raw[name] = _component(name, args, out_dir)
    figures += _core_figures(raw["bench_core"])
    figures += _visca_figures(raw["bench_visca"])
    figures += _render_figures(raw["bench_render"])
    lockstep = _lockstep_figures(quick)
    raw["lockstep"] = lockstep["raw"]
    figures += lockstep["figures"]
    figures += _daemon_figures(raw["bench_daemon"], quick)
    doc = {"schema": BENCH_SCHEMA, "quick": quick, "figures": figures, "raw": raw}
    path = out_dir / "bench.json"
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n", encoding="utf-8")
    for f in figures:
        verdict = {True: "PASS", False: "FAIL", None: "  - "}[f.get("ok")]
        base = (
            f" vs {f['baseline']} {f['baseline_value']:.4g}"
            if f.get("baseline_value") is not None
            else ""
        )
        ratio = f" ratio {f['ratio']:.3g}" if f.get("ratio") is not None else ""
        value = f["value"]
        shown = f"{value:.4g}" if isinstance(value, float | int) else str(value)
        print(f"[{verdict}] {f['name']}: {shown} {f['unit']}{base}{ratio}  ({f['goal']})")
    print(f"bench: {path}")
    return 0


# -- components ------------------------------------------------------------------------------


def _component(name: str, args: list[str], out_dir: Path) -> dict[str, Any]:
    module = f"hil.{name}"
    if importlib.util.find_spec(module) is None:
        return {"missing": f"{module} is not in this tree yet"}
    out = out_dir / f"{name}.json"
    cmd = [sys.executable, "-m", module, *args, "--out", str(out)]
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
    wall = time.perf_counter() - t0
    if not out.exists():
        tail = (proc.stderr or proc.stdout)[-2000:]
        return {"error": f"{module} exited {proc.returncode} without results: {tail}"}
    data: dict[str, Any] = json.loads(out.read_text(encoding="utf-8"))
    data["_wall_s"] = wall
    data["_exit"] = proc.returncode
    return data


def _figure(
    name: str,
    value: float | None,
    unit: str,
    goal: str,
    *,
    baseline: str | None = None,
    baseline_value: float | None = None,
    ratio: float | None = None,
    ok: bool | None = None,
) -> dict[str, Any]:
    return {
        "name": name,
        "value": value,
        "unit": unit,
        "baseline": baseline,
        "baseline_value": baseline_value,
        "ratio": ratio,
        "goal": goal,
        "ok": ok,
    }


def _core_figures(core: dict[str, Any]) -> list[dict[str, Any]]:
    if "core" not in core:
        return [_figure("core CPU per tracking frame", None, "ms", "≤ 2 ms", ok=None)]
    mean = core["core"]["mean_ms"]
    naive = core["baseline_naive_full_frame"]["mean_ms"]
    speedup = naive / mean if mean > 0 else None
    return [
        _figure(
            "core CPU per tracking frame",
            mean,
            "ms",
            "≤ 2 ms (docs/design.md §10)",
            baseline="budget",
            baseline_value=2.0,
            ratio=mean / 2.0,
            ok=mean <= 2.0,
        ),
        _figure(
            "core speed-up vs naive full-frame",
            speedup,
            "×",
            "≥ 10× (docs/design.md §10)",
            baseline="naive full-frame gradient + contour + cost (ms)",
            baseline_value=naive,
            ratio=speedup,
            ok=None if speedup is None else speedup >= 10.0,
        ),
    ]


def _visca_figures(visca: dict[str, Any]) -> list[dict[str, Any]]:
    paced = visca.get("paced_9600", {}).get("command")
    unpaced = visca.get("unpaced", {}).get("command")
    if not paced or not unpaced:
        return [_figure("VISCA command round trip", None, "ms", "overhead ≪ wire time")]
    return [
        _figure(
            "VISCA command round trip at 9600 baud",
            paced["median_ms"],
            "ms",
            "close to the wire time of its bytes",
            baseline="wire time (ms)",
            baseline_value=paced["wire_ms_at_9600"],
            ratio=paced["ratio_to_wire"],
        ),
        _figure(
            "VISCA driver overhead (unpaced round trip)",
            unpaced["median_ms"],
            "ms",
            "≪ wire time",
            baseline="wire time at 9600 baud (ms)",
            baseline_value=unpaced["wire_ms_at_9600"],
            ratio=unpaced["ratio_to_wire"],
            ok=unpaced["ratio_to_wire"] < 0.25,
        ),
    ]


def _render_figures(render: dict[str, Any]) -> list[dict[str, Any]]:
    overall = render.get("overall")
    if not overall:
        return [_figure("simulator render time", None, "ms", "≤ 5 ms")]
    budget = float(render.get("budget_ms", 5.0))
    return [
        _figure(
            "simulator render time per 640×480 frame (p95)",
            overall["p95_ms"],
            "ms",
            f"≤ {budget:g} ms (issue 3)",
            baseline="budget",
            baseline_value=budget,
            ratio=overall["p95_ms"] / budget,
            ok=overall["p95_ms"] <= budget,
        )
    ]


def _lockstep_figures(quick: bool) -> dict[str, Any]:
    """Depth rate vs limit, and replay frames/s, from one lock-step session with a recording."""
    from dffd.core.lens import Lens
    from dffd.recording import RecordingReader, RecordingWriter
    from dffd.replay import replay
    from hil.lockstep import daemon_config, pipeline_config, run_session
    from hil.runner import RecordingSink
    from hil.scenario import load_scenario
    from hil.simbuild import build_session

    duration = QUICK_RATE_DURATION_S if quick else RATE_DURATION_S
    scenario = load_scenario(RATE_SCENARIO)
    traj = dict(scenario.expand())[RATE_CASE]
    seed = scenario.seeds[0]
    session = build_session(scenario, traj, seed)
    lens = Lens.from_toml(session.lens_path)
    with tempfile.TemporaryDirectory(prefix="hil-bench-") as tmp:
        rec = Path(tmp) / "rec"
        with RecordingWriter(rec, session.fps, session.frame_size, lens.to_meta()) as writer:
            res = run_session(
                scenario, RATE_CASE, traj, seed, duration_s=duration, recorder=RecordingSink(writer)
            )
        reader = RecordingReader(rec)
        frames = [(reader.load(r), r.tag) for r in reader.records]
        t0 = time.perf_counter()
        replay(frames, lens, pipeline_config(scenario, daemon_config()))
        replay_s = time.perf_counter() - t0
    fps_replay = len(frames) / replay_s if replay_s > 0 else None
    limit = res.depth_limit_hz
    ratio = res.depth_hz / limit if limit else None
    figures = [
        _figure(
            "depth measurements per second (lock-step, static 4 m)",
            res.depth_hz,
            "Hz",
            "≥ 90% of the theoretical limit (docs/design.md §10)",
            baseline="scheduler limit (Hz)",
            baseline_value=limit,
            ratio=ratio,
            ok=None if ratio is None else ratio >= 0.9,
        ),
        _figure(
            "replay frames per second (frames decoded beforehand)",
            fps_replay,
            "frames/s",
            "faster than the camera's frame rate",
            baseline="camera frame rate (fps)",
            baseline_value=session.fps,
            ratio=None if fps_replay is None else fps_replay / session.fps,
            ok=None if fps_replay is None else fps_replay >= session.fps,
        ),
        _figure(
            "lock-step speed (scenario s per wall s)",
            res.duration_s / res.wall_s if res.wall_s > 0 else None,
            "×",
            "minutes of scenario in seconds",
            baseline="real time",
            baseline_value=1.0,
        ),
    ]
    raw = {
        "scenario": f"{RATE_SCENARIO}/{RATE_CASE}",
        "duration_s": duration,
        "depth_hz": res.depth_hz,
        "depth_limit_hz": limit,
        "bursts": len(res.bursts),
        "accepted": res.accepted_bursts,
        "replay_frames": len(frames),
        "replay_s": replay_s,
        "lockstep_wall_s": res.wall_s,
    }
    return {"figures": figures, "raw": raw}


def _daemon_figures(daemon: dict[str, Any], quick: bool) -> list[dict[str, Any]]:
    latency = _find_latency(daemon)
    source = "hil.bench_daemon"
    if latency is None:
        latency = _realtime_latency(quick)
        source = "hil real-time run (approach)"
    if latency is None:
        return [_figure("exposure → MQTT latency", None, "ms", "p50 ≤ 10 ms, p99 ≤ 30 ms")]
    p50, p99 = latency
    lag_ms = _sim_delivery_lag_ms()
    net = _figure(
        "frame delivery → MQTT latency p50 (exposure latency minus the simulated capture lag)",
        p50 - lag_ms,
        "ms",
        "the daemon's own share of the latency",
        baseline="simulated capture lag exposure/2 + latency_frames/fps (ms)",
        baseline_value=lag_ms,
    )
    return [
        net,
        _figure(
            f"exposure → MQTT latency p50 ({source})",
            p50,
            "ms",
            "≤ 10 ms at 30 fps (docs/design.md §10)",
            baseline="goal",
            baseline_value=10.0,
            ratio=p50 / 10.0,
            ok=p50 <= 10.0,
        ),
        _figure(
            f"exposure → MQTT latency p99 ({source})",
            p99,
            "ms",
            "≤ 30 ms at 30 fps (docs/design.md §10)",
            baseline="goal",
            baseline_value=30.0,
            ratio=p99 / 30.0,
            ok=p99 <= 30.0,
        ),
    ]


def _sim_delivery_lag_ms() -> float:
    from drivers.sim.config import load_sim_camera_config
    from drivers.sim.resources import reference_camera_file

    cfg = load_sim_camera_config(reference_camera_file())
    cap = cfg.capture
    return 1e3 * (cap.exposure_s / 2.0 + cap.capture_latency_frames / cap.fps)


def _find_latency(data: Any) -> tuple[float, float] | None:
    """p50/p99 (ms) of the first block that has both, searching a bench_daemon result."""
    if isinstance(data, dict):
        keys = {k.lower(): k for k in data}
        p50 = next((data[keys[k]] for k in ("p50_ms", "latency_p50_ms") if k in keys), None)
        p99 = next((data[keys[k]] for k in ("p99_ms", "latency_p99_ms") if k in keys), None)
        if isinstance(p50, int | float) and isinstance(p99, int | float):
            return float(p50), float(p99)
        for key, value in data.items():
            if "latency" in str(key).lower() and "goal" not in str(key).lower():
                if isinstance(value, dict) and {"p50", "p99"} <= set(value):
                    return float(value["p50"]), float(value["p99"])
                found = _find_latency(value)
                if found is not None:
                    return found
    return None


def _realtime_latency(quick: bool) -> tuple[float, float] | None:
    from hil.realtime import run_realtime
    from hil.report import build_report
    from hil.runner import RunOptions
    from hil.scenario import load_scenario

    scenario = load_scenario("approach").shortened(10.0 if quick else 30.0)
    with tempfile.TemporaryDirectory(prefix="hil-bench-rt-") as tmp:
        options = RunOptions(out_dir=Path(tmp), fast=False, plots=False, progress=False)
        try:
            results = run_realtime(scenario, options)
        except (RuntimeError, OSError) as exc:
            logger.warning("real-time latency run failed: %s", exc)
            return None
    lat = build_report(results, scenario.name)["latency"]
    return None if lat is None else (lat["p50_ms"], lat["p99_ms"])
