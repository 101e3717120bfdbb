"""``python -m hil soak --minutes N``: the live daemon on the simulator over a long run.

Starts ``python -m dffd run --no-console`` (simulated camera on a pty, a mosquitto on a free
loopback port as :mod:`hil.realtime` starts it), subscribes to ``…/estimate`` and
``…/measurement`` like a user and samples the daemon's ``/proc`` once a second. Reports:

* start → first estimate (process start to the first ``…/estimate`` at the subscriber);
* RSS slope in MiB/hour (least squares over the last half of the run, and not before
  ``WARMUP_S``) and min/max;
* CPU % of one core (utime + stime over the run after the first estimate), and the service's
  share: minus the simulator's threads (``sim-render``, its renderer; ``sim-camera``, its VISCA
  device), and
  each thread's share (the daemon runs under :mod:`hil.threadnames` so the kernel knows them);
* exposure → subscriber latency percentiles (reception minus the payload's ``t_mono``), that
  minus the simulated capture chain's nominal delivery lag, and frame delivered → subscriber
  (the service's own share, matched through ``…/sim/truth``; see :func:`_receive`);
* per window of ``--window`` seconds: estimate and measurement rates, latency p50/p99, CPU %, RSS.

``fresh_kernel_cache`` starts the daemon with an empty ``NUMBA_CACHE_DIR`` (a fresh install that
skipped ``python -m dffd.warmup``): the daemon then starts on the kernels' NumPy twins while a
background process compiles them.

Writes ``soak.json`` and ``soak.png`` into ``--out``. Figures only, no verdicts asserted.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil import memprobe

# The bench's own helpers (private to their module today; one place to start a broker and read
# /proc).
from hil.realtime import (
    DAEMON_START_TIMEOUT_S,
    MQTT_CONNECT_TIMEOUT_S,
    REPO_ROOT,
)
from hil.realtime import _cpu_times as cpu_times
from hil.realtime import _free_port as free_port
from hil.realtime import _rss_kib as rss_kib
from hil.realtime import _start_mosquitto as start_mosquitto
from hil.realtime import _stop as stop_process

# /proc sampling period: RSS moves slowly, one sample a second resolves 0.1 MiB over minutes.
SAMPLE_PERIOD_S = 1.0
# Samples before this are start-up (imports, first acquisition, first bursts): not in the slope.
WARMUP_S = 10.0
# The slope is fitted over the last part of the run only: RSS settles over the first minutes
# (allocator arenas, bounded histories filling: +11 MiB in the first 2 minutes, measured), and
# that settling is not growth.
SLOPE_FRACTION = 0.5
# With an empty kernel cache the daemon compiles every kernel before its first estimate: ~25 s of
# CPU, several times that on a 2-core machine shared with other work.
FRESH_START_TIMEOUT_S = 240.0
# The broker connection is retried this often while the daemon starts.
CONNECT_RETRY_S = 0.2
DEFAULT_WINDOW_S = 60.0
# `git describe` answers in milliseconds; a hung git must not hold up a result.
GIT_TIMEOUT_S = 10.0
# Latency samples kept (30 estimates/s for 24 h): bounds this process's own memory.
MAX_LATENCY_SAMPLES = 30 * 86_400
# Delivery times of the last frames kept to match estimates against: 10 s at 30 fps.
TRUTHS_KEPT = 300
MIB = 1024.0
# hil.memprobe's samples, in --out.
PROBE_FILE = "probe.jsonl"
# The simulator's threads (kernel names set by hil.threadnames): its frame source renders in
# "sim-render" (drivers/sim/source.py), its VISCA device serves from "sim-camera"
# (dffd/daemon/simthread.py). Older trees rendered in asyncio's default executor ("asyncio_0",
# "asyncio_1", …), which the daemon itself uses only at start and stop.
SIM_THREAD_PREFIXES = ("sim-render", "sim-camera", "asyncio_")


@dataclass
class _Trace:
    """What the subscriber saw, with monotonic reception times."""

    started: float
    first_estimate: float | None = None
    estimates: list[tuple[float, float]] = field(default_factory=list)  # (received, latency s)
    measurements: list[float] = field(default_factory=list)  # received
    samples: list[tuple[float, float, int]] = field(default_factory=list)  # (t, cpu s, rss KiB)
    # per sample: RSS of anonymous memory (heap, Python's arenas, stacks) and of mapped files
    # (code and data of the libraries), KiB — which of the two grows
    rss_split: list[tuple[int, int]] = field(default_factory=list)
    threads: list[dict[str, float]] = field(default_factory=list)  # thread name → CPU s, per sample
    # Frame delivered to the daemon → estimate at this subscriber (s), from the …/sim/truth
    # message of the same frame (see _receive).
    delivered: list[float] = field(default_factory=list)
    truths: dict[float, float] = field(default_factory=dict)  # frame t_mono → delivery wall time


def run_soak(
    seconds: float,
    out_dir: Path,
    scenario: str = "static",
    window_s: float = 0,
    *,
    fresh_kernel_cache: bool = False,
    probe: int | None = None,
    daemon_env: dict[str, str] | None = None,
) -> int:
    """Run the soak for ``seconds`` after the first estimate; write soak.json and soak.png.

    ``probe`` (None: off) runs the daemon under :mod:`hil.memprobe`, with tracemalloc at that
    traceback depth when > 0; its samples go to ``probe.jsonl`` and a summary into soak.json.
    ``daemon_env`` is added to the daemon's environment (A/B runs).
    """
    window = window_s if window_s > 0 else min(DEFAULT_WINDOW_S, max(seconds / 10.0, 1.0))
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    load_before = os.getloadavg()
    try:
        trace = asyncio.run(
            _soak(seconds, scenario, out_dir, fresh_kernel_cache, probe, daemon_env or {})
        )
    except (RuntimeError, TimeoutError) as exc:
        why = str(exc) or "no estimate in time"
        print(f"hil soak: {why}; see {out_dir / 'daemon.log'}", file=sys.stderr)
        return 1
    result = summarize(trace, seconds, window, sim_delivery_lag_ms())
    result["scenario"] = scenario
    result["fresh_kernel_cache"] = fresh_kernel_cache
    if daemon_env:
        result["daemon_env"] = daemon_env
    if probe is not None:
        result["probe"] = summarize_probe(
            out_dir / PROBE_FILE, trace.started, trace.first_estimate, result
        )
    # Where and when: a long soak's figures are quoted by the bench (hil.benchmarks), so they
    # must say what they were measured on. Load above 2 means the 2 cores were shared.
    result["t"] = started
    result["commit"] = git_commit()
    result["load_average"] = {"before": list(load_before), "after": list(os.getloadavg())}
    (out_dir / "soak.json").write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    plot(result, out_dir / "soak.png")
    print(format_summary(result))
    print(f"soak: {out_dir / 'soak.json'}, {out_dir / 'soak.png'}")
    return 0


def summarize(
    trace: _Trace, seconds: float, window_s: float, delivery_lag_ms: float
) -> dict[str, Any]:
    """The soak.json object: totals, RSS slope, latency percentiles and per-window series."""
    t0 = trace.first_estimate if trace.first_estimate is not None else trace.started
    kept = [i for i, (t, _, _) in enumerate(trace.samples) if t >= t0]
    samples = [
        (trace.samples[i][0] - t0, trace.samples[i][1], trace.samples[i][2] / MIB) for i in kept
    ]
    threads = [trace.threads[i] for i in kept if i < len(trace.threads)]
    lat = np.array([lat for _, lat in trace.estimates]) * 1e3
    delivered = np.array(trace.delivered) * 1e3
    last = max([r for r, _ in trace.estimates] + [t for t, _, _ in trace.samples], default=t0)
    run_s = max(last - t0, 0.0)
    cpu_pct = (
        100.0 * (samples[-1][1] - samples[0][1]) / (samples[-1][0] - samples[0][0])
        if len(samples) > 1 and samples[-1][0] > samples[0][0]
        else None
    )
    shares = (
        thread_shares(threads[0], threads[-1], samples[-1][0] - samples[0][0])
        if len(threads) == len(samples) and len(threads) > 1
        else {}
    )
    sim_pct = (
        sum(v for k, v in shares.items() if k.startswith(SIM_THREAD_PREFIXES)) if shares else None
    )
    slope_from = max(WARMUP_S, (1.0 - SLOPE_FRACTION) * run_s)
    steady = [(t, rss) for t, _, rss in samples if t >= slope_from]
    slope = _slope_per_hour(steady)
    split = [trace.rss_split[i] for i in kept if i < len(trace.rss_split)]
    parts: dict[str, float | None] = {}
    if len(split) == len(samples):
        for k, name in enumerate(("anon", "file")):
            part = [(t, kib[k] / MIB) for (t, _, _), kib in zip(samples, split, strict=True)]
            parts[f"{name}_slope_mib_per_hour"] = _slope_per_hour(
                [(t, v) for t, v in part if t >= slope_from]
            )
            parts[f"{name}_last_mib"] = part[-1][1] if part else None
    windows = []
    for start in np.arange(0.0, max(run_s, 0.0), window_s):
        end = start + window_s
        est = [lat for r, lat in trace.estimates if start <= r - t0 < end]
        meas = sum(1 for r in trace.measurements if start <= r - t0 < end)
        win = [s for s in samples if start <= s[0] <= end]
        span = min(end, run_s) - start
        if span < window_s / 2:  # a trailing stub would show rates of a few messages
            continue
        w_lat = np.array(est) * 1e3
        windows.append(
            {
                "t_s": float(start),
                "estimate_hz": len(est) / span,
                "measurement_hz": meas / span,
                "latency_p50_ms": _pct(w_lat, 50),
                "latency_p99_ms": _pct(w_lat, 99),
                "cpu_pct": 100.0 * (win[-1][1] - win[0][1]) / (win[-1][0] - win[0][0])
                if len(win) > 1 and win[-1][0] > win[0][0]
                else None,
                "rss_mib": win[-1][2] if win else None,
            }
        )
    rss_all = [rss for _, _, rss in samples]
    return {
        "schema": 1,
        "requested_s": seconds,
        "run_s": run_s,
        "start_to_first_estimate_s": None
        if trace.first_estimate is None
        else trace.first_estimate - trace.started,
        "estimates": len(trace.estimates),
        "measurements": len(trace.measurements),
        "estimate_hz": len(trace.estimates) / run_s if run_s > 0 else None,
        "cpu_pct_one_core": cpu_pct,
        "simulator_cpu_pct_one_core": sim_pct,
        "service_cpu_pct_one_core": None
        if cpu_pct is None or sim_pct is None
        else cpu_pct - sim_pct,
        "thread_cpu_pct_one_core": shares,
        "rss_mib": {
            "min": min(rss_all, default=None),
            "max": max(rss_all, default=None),
            "slope_mib_per_hour": slope,
            "slope_from_s": slope_from,
            "samples": len(steady),
        }
        | parts,
        "latency_ms": {
            "exposure_to_subscriber": {p: _pct(lat, q) for p, q in _PCTS},
            "daemon_share": {p: _pct(lat - delivery_lag_ms, q) for p, q in _PCTS},
            "delivered_to_subscriber": {p: _pct(delivered, q) for p, q in _PCTS},
            "delivered_matched": len(trace.delivered),
            "sim_delivery_lag_ms": delivery_lag_ms,
        },
        "window_s": window_s,
        "windows": windows,
        "rss_series": [[t, rss] for t, _, rss in samples],
    }


def summarize_probe(
    path: Path, started: float, first_estimate: float | None, result: dict[str, Any]
) -> dict[str, Any]:
    """Slopes (MiB/h, over the soak's slope window) of what the probe saw, and the growth sites.

    The probe's clock starts with the daemon process (a few ms after ``started``); its samples
    are shifted to the soak's time axis (t = 0 at the first estimate).
    """
    try:
        rows = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
    except (OSError, ValueError) as exc:
        return {"missing": f"{path}: {exc}"}
    shift = (first_estimate if first_estimate is not None else started) - started
    slope_from = result["rss_mib"]["slope_from_s"]
    series: dict[str, list[tuple[float, float]]] = {}
    for row in rows:
        t = row["t_s"] - shift
        info = row.get("mallinfo2") or {}
        values = {
            "rss_anon": row["rss_anon_kib"] / MIB,
            "heap_from_os": (info.get("arena", 0) + info.get("hblkhd", 0)) / MIB / MIB,
            "heap_in_use": (info.get("uordblks", 0) + info.get("hblkhd", 0)) / MIB / MIB,
            "heap_free": info.get("fordblks", 0) / MIB / MIB,
        }
        for kind, kib in (row.get("anon_by_mapping_kib") or {}).items():
            values[f"anon_{kind}"] = kib / MIB if not kind.endswith("_count") else float(kib)
        if "traced_bytes" in row:
            values["traced"] = row["traced_bytes"] / MIB / MIB
            values["numpy"] = row["numpy_bytes"] / MIB / MIB
            values["gc_objects"] = float(row["gc_objects"])
            values["asyncio_tasks"] = float(row["asyncio_tasks"])
        for key, v in values.items():
            series.setdefault(key, []).append((t, v))
    out: dict[str, Any] = {"samples": len(rows)}
    for key, pts in series.items():
        steady = [(t, v) for t, v in pts if t >= slope_from]
        out[key] = {
            "last": pts[-1][1],
            "slope_per_hour": _slope_per_hour(steady),
            "min_steady": min((v for _, v in steady), default=None),
            "max_steady": max((v for _, v in steady), default=None),
        }
    last_growth = [r["top_growth"] for r in rows if "top_growth" in r]
    if last_growth:
        out["top_growth_since_baseline"] = last_growth[-1]
    return out


def format_summary(result: dict[str, Any]) -> str:
    """Human-readable lines of a soak result."""

    def f(v: float | None, fmt: str = ".1f") -> str:
        return "–" if v is None else format(v, fmt)

    rss = result["rss_mib"]
    lat = result["latency_ms"]
    e2s, own = lat["exposure_to_subscriber"], lat["daemon_share"]
    head = (
        f"soak {f(result['run_s'])} s: start -> first estimate "
        f"{f(result['start_to_first_estimate_s'])} s; {result['estimates']} estimates "
        f"({f(result['estimate_hz'])}/s), {result['measurements']} measurements"
    )
    cpu = (
        f"CPU {f(result['cpu_pct_one_core'])} % of one core (service without the simulator "
        f"{f(result.get('service_cpu_pct_one_core'))} %); RSS {f(rss['min'])}-"
        f"{f(rss['max'])} MiB, slope {f(rss['slope_mib_per_hour'], '.2f')} MiB/h "
        f"(least squares after {rss['slope_from_s']:.0f} s, {rss['samples']} samples; "
        f"anonymous {f(rss.get('anon_slope_mib_per_hour'), '.2f')}, mapped files "
        f"{f(rss.get('file_slope_mib_per_hour'), '.2f')} MiB/h)"
    )
    dts = lat.get("delivered_to_subscriber", {})
    latency = (
        f"exposure -> subscriber p50 {f(e2s['p50'])} p99 {f(e2s['p99'])} ms; "
        f"minus the nominal sim delivery lag ({lat['sim_delivery_lag_ms']:.1f} ms) p50 "
        f"{f(own['p50'])} p99 {f(own['p99'])} ms; frame delivered -> subscriber p50 "
        f"{f(dts.get('p50'))} p99 {f(dts.get('p99'))} ms"
    )
    return "\n".join([head, cpu, latency])


def plot(result: dict[str, Any], path: Path) -> None:
    """RSS (with its fit), CPU %, latency p50/p99 and rates over time, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(10, 10))
    rss = np.array(result["rss_series"]) if result["rss_series"] else np.zeros((0, 2))
    wins = result["windows"]
    tw = [w["t_s"] + result["window_s"] / 2 for w in wins]
    ax = axes[0]
    ax.plot(rss[:, 0], rss[:, 1], lw=1, label="RSS")
    slope = result["rss_mib"]["slope_mib_per_hour"]
    if slope is not None and len(rss):
        steady = rss[rss[:, 0] >= result["rss_mib"]["slope_from_s"]]
        mid_t, mid_r = steady[:, 0].mean(), steady[:, 1].mean()
        ax.plot(
            steady[:, 0],
            mid_r + slope / 3600.0 * (steady[:, 0] - mid_t),
            "k--",
            lw=1,
            label=f"fit {slope:.2f} MiB/h",
        )
    ax.set_ylabel("RSS (MiB)")
    ax.legend(loc="best", fontsize="small")
    axes[1].plot(tw, [w["cpu_pct"] for w in wins], marker=".")
    axes[1].set_ylabel("CPU (% of a core)")
    axes[2].plot(tw, [w["latency_p50_ms"] for w in wins], marker=".", label="p50")
    axes[2].plot(tw, [w["latency_p99_ms"] for w in wins], marker=".", label="p99")
    axes[2].set_ylabel("exposure → sub (ms)")
    axes[2].legend(loc="best", fontsize="small")
    axes[3].plot(tw, [w["estimate_hz"] for w in wins], marker=".", label="estimates/s")
    axes[3].plot(tw, [w["measurement_hz"] for w in wins], marker=".", label="measurements/s")
    axes[3].set_ylabel("rate (Hz)")
    axes[3].set_xlabel("t since first estimate (s)")
    axes[3].legend(loc="best", fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


_PCTS = (("p50", 50), ("p90", 90), ("p99", 99), ("max", 100))


def _pct(values: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def _slope_per_hour(points: list[tuple[float, float]]) -> float | None:
    """Least-squares slope of (t s, MiB) in MiB/hour."""
    if len(points) < 3:
        return None
    t = np.array([p[0] for p in points])
    y = np.array([p[1] for p in points])
    if float(np.ptp(t)) <= 0:
        return None
    slope = float(np.polyfit(t, y, 1)[0])
    return slope * 3600.0 if math.isfinite(slope) else None


async def _soak(  # noqa: PLR0917 - one private call site
    seconds: float,
    scenario: str,
    out_dir: Path,
    fresh_kernel_cache: bool,
    probe: int | None,
    daemon_env: dict[str, str],
) -> _Trace:
    work = Path(tempfile.mkdtemp(prefix="hil-soak-"))
    port = free_port()
    broker = start_mosquitto(work, port)
    env = dict(os.environ)
    env["DFFD_MQTT__URL"] = f"mqtt://127.0.0.1:{port}" if broker else "embedded"
    if broker is None:
        env["DFFD_MQTT__EMBEDDED_PORT"] = str(port)
    env.update(
        {
            "DFFD_LOG__DIR": str(work / "log"),
            "DFFD_MQTT__TOPIC_PREFIX": "dffd",
            "DFFD_CAMERA__DRIVER": "sim",
            "DFFD_CAPTURE__SOURCE": "sim",
            "DFFD_SIM__SCENARIO": scenario,
        }
    )
    if fresh_kernel_cache:
        env["NUMBA_CACHE_DIR"] = str(work / "numba-cache")
    shim = "hil.threadnames"
    if probe is not None:
        shim = "hil.memprobe"
        (out_dir / PROBE_FILE).unlink(missing_ok=True)
        env[memprobe.OUT_ENV] = str(out_dir / PROBE_FILE)
        env[memprobe.TRACEMALLOC_ENV] = str(probe)
    env.update(daemon_env)
    trace = _Trace(started=time.monotonic())
    with (out_dir / "daemon.log").open("wb") as log:
        # The daemon is this repository's own CLI run with this interpreter.
        daemon = subprocess.Popen(  # noqa: ASYNC220, S603 - started once, stopped in finally
            [sys.executable, "-m", shim, "dffd", "run", "--no-console"],
            cwd=REPO_ROOT,
            env=env,
            stdout=log,
            stderr=log,
        )
        try:
            async with asyncio.TaskGroup() as tg:
                sampler = tg.create_task(_sample(daemon.pid, trace))
                start_s = FRESH_START_TIMEOUT_S if fresh_kernel_cache else DAEMON_START_TIMEOUT_S
                await _subscribe(daemon, port, trace, seconds, start_s)
                sampler.cancel()
        finally:
            stop_process(daemon)
            if broker is not None:
                stop_process(broker)
    return trace


async def _sample(pid: int, trace: _Trace) -> None:
    while True:
        user, system = cpu_times(pid)
        trace.threads.append(thread_cpu_s(pid))
        trace.samples.append((time.monotonic(), user + system, rss_kib(pid)))
        trace.rss_split.append(_rss_anon_file_kib(pid))
        await asyncio.sleep(SAMPLE_PERIOD_S)


def _rss_anon_file_kib(pid: int) -> tuple[int, int]:
    """RssAnon and RssFile of ``pid`` (KiB; 0 where /proc does not say)."""
    found = {"RssAnon:": 0, "RssFile:": 0}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key = line.split(maxsplit=1)[0] if line else ""
            if key in found:
                found[key] = int(line.split()[1])
    except OSError:
        pass
    return found["RssAnon:"], found["RssFile:"]


def git_commit() -> str | None:
    """``git describe --always --dirty`` of this tree (None outside a git checkout)."""
    try:
        proc = subprocess.run(
            ["git", "describe", "--always", "--dirty"],  # noqa: S607 - git from PATH
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=False,
            timeout=GIT_TIMEOUT_S,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout.strip() or None


def sim_delivery_lag_ms() -> float:
    """Mid-exposure → delivery of the reference simulated camera: exposure/2 + its latency."""
    from drivers.sim.config import load_sim_camera_config
    from drivers.sim.resources import reference_camera_file

    cap = load_sim_camera_config(reference_camera_file()).capture
    return 1e3 * (cap.exposure_s / 2.0 + cap.capture_latency_frames / cap.fps)


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) of each live thread of ``pid``, summed by kernel name."""
    out: dict[str, float] = {}
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return out
    tick = os.sysconf("SC_CLK_TCK")
    for task in tasks:
        try:
            head, tail = (task / "stat").read_text().rsplit(")", 1)
        except OSError:  # the thread ended between the listing and the read
            continue
        name = head.split("(", 1)[1]
        fields = tail.split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


def thread_shares(
    first: dict[str, float], last: dict[str, float], span_s: float
) -> dict[str, float]:
    """CPU % of one core of each thread name between two :func:`thread_cpu_s` samples."""
    if span_s <= 0:
        return {}
    return {
        name: 100.0 * (cpu - first.get(name, 0.0)) / span_s for name, cpu in sorted(last.items())
    }


async def _subscribe(
    daemon: subprocess.Popen[bytes], port: int, trace: _Trace, seconds: float, start_s: float
) -> None:
    import aiomqtt

    deadline = trace.started + start_s
    while True:
        if daemon.poll() is not None:
            raise RuntimeError(f"the daemon exited with status {daemon.returncode}; see daemon.log")
        try:
            async with aiomqtt.Client("127.0.0.1", port, timeout=MQTT_CONNECT_TIMEOUT_S) as client:
                await client.subscribe("dffd/+/estimate")
                await client.subscribe("dffd/+/measurement")
                await client.subscribe("dffd/+/sim/truth")
                await _receive(client, trace, seconds, start_s)
                return
        except aiomqtt.MqttError:
            if time.monotonic() > deadline:
                raise RuntimeError("no MQTT broker came up for the daemon") from None
            await asyncio.sleep(CONNECT_RETRY_S)


async def _receive(client: Any, trace: _Trace, seconds: float, start_s: float) -> None:
    """Record estimates, measurements and the delivery time of each frame until done.

    The daemon publishes a frame's ``…/sim/truth`` on its event loop right after handing the
    frame to the estimator, stamped with the wall time then (``t``): that is when the frame was
    delivered to the service (after the simulator rendered it). An estimate of the same frame
    (same ``t_mono``) received at wall time ``now`` took ``now − t`` in the service, plus the
    broker; the daemon and this process share the machine's clock.
    """
    async with asyncio.timeout(start_s + seconds + 10.0):
        async for message in client.messages:
            now = time.monotonic()
            wall = time.time()
            topic = message.topic.value
            if topic.endswith("/measurement"):
                trace.measurements.append(now)
                continue
            payload = json.loads(bytes(message.payload))
            if topic.endswith("/sim/truth"):
                trace.truths[float(payload["t_mono"])] = float(payload["t"])
                if len(trace.truths) > TRUTHS_KEPT:
                    del trace.truths[next(iter(trace.truths))]
                continue
            if trace.first_estimate is None:
                trace.first_estimate = now
            if not payload.get("replayed") and len(trace.estimates) < MAX_LATENCY_SAMPLES:
                trace.estimates.append((now, now - float(payload["t_mono"])))
                delivered = trace.truths.get(float(payload["t_mono"]))
                if delivered is not None:
                    trace.delivered.append(wall - delivered)
            if now - trace.first_estimate >= seconds:
                return
