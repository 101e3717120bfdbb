"""Benchmark of the real daemon (docs/design.md §10): latency, depth-measurement rate, CPU and RSS.

Runs ``python -m dffd run`` as a subprocess against the simulated camera on a pty and a real
mosquitto on a free loopback port (the embedded amqtt broker if mosquitto is not installed),
subscribes to its topics from this process and measures, over ``--seconds`` of steady running:

* exposure → subscriber latency of ``…/estimate`` (``time.monotonic()`` at receipt minus the
  payload's ``t_mono``, the frame's mid-exposure time; CLOCK_MONOTONIC is system-wide) p50/p99;
* achieved depth measurements per second (``…/measurement`` messages, and accepted ones) as a
  ratio of the theoretical limit the daemon computes from its configuration (``status.rates``);
* the daemon's CPU % (utime+stime from /proc, of one core) and RSS (min/max/last, and the growth
  between the first and last quarter of the run).

``python -m hil.bench_daemon [--seconds 300] [--scenario static] [--out bench_daemon.json]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiomqtt

# Start-up of the daemon (sim camera, broker connection, first frames) on a loaded machine.
STARTUP_TIMEOUT_S = 30.0
# The daemon exits within its own SHUTDOWN_TIMEOUT_S (10 s).
EXIT_TIMEOUT_S = 15.0
# Warm-up discarded before measuring (acquisition, first bursts, filter settling).
WARMUP_S = 5.0
# /proc sampling period for CPU and RSS.
SAMPLE_PERIOD_S = 1.0
# mosquitto binds within milliseconds; allow for a loaded machine.
BROKER_START_TIMEOUT_S = 5.0
PORT_POLL_S = 0.05


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print a summary and write JSON with ``--out``."""
    parser = argparse.ArgumentParser(prog="python -m hil.bench_daemon", description=__doc__)
    parser.add_argument("--seconds", type=float, default=300.0, help="measured run length")
    parser.add_argument("--scenario", default="static", help="sim.scenario of the daemon")
    parser.add_argument("--out", type=Path, help="write the results as JSON here")
    args = parser.parse_args(argv)
    result = asyncio.run(_bench(args.seconds, args.scenario))
    print(json.dumps(result, indent=2))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


async def _bench(seconds: float, scenario: str) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="dffd-bench-") as tmp:
        work = Path(tmp)
        port = _free_port()
        broker = _start_mosquitto(work, port)
        url = f"mqtt://127.0.0.1:{port}" if broker is not None else "embedded"
        config = work / "dffd.toml"
        config.write_text(
            f'[sim]\nscenario = "{scenario}"\nseed = 1\n'
            f'[mqtt]\nurl = "{url}"\nembedded_port = {port}\n'
            f'[log]\ndir = "{work / "log"}"\nlevel = "WARNING"\n',
            encoding="utf-8",
        )
        err = (work / "daemon.err").open("wb")
        daemon = _spawn_daemon(config, work, err)
        try:
            return await _measure(daemon, port, seconds, scenario, broker is not None)
        finally:
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGTERM)
                try:
                    daemon.wait(EXIT_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    daemon.kill()
            err.close()
            if broker is not None:
                broker.terminate()
                broker.wait(EXIT_TIMEOUT_S)


async def _measure(
    daemon: subprocess.Popen[bytes], port: int, seconds: float, scenario: str, mosquitto: bool
) -> dict[str, Any]:
    latencies: list[float] = []
    measurements: list[tuple[float, bool]] = []
    limits: list[float] = []
    samples: list[tuple[float, float, int]] = []  # (t, cpu seconds, rss bytes)
    tick = os.sysconf("SC_CLK_TCK")
    async with asyncio.timeout(STARTUP_TIMEOUT_S):
        while True:
            try:
                client = aiomqtt.Client("127.0.0.1", port)
                await client.__aenter__()
                break
            except aiomqtt.MqttError:
                await asyncio.sleep(PORT_POLL_S)
    try:
        await client.subscribe("dffd/sim/#", qos=0)
        # Wait for the first estimate, then warm up.
        t_first: float | None = None
        t_start = t_end = next_sample = math.inf
        async with asyncio.timeout(STARTUP_TIMEOUT_S + WARMUP_S + seconds + 30.0):
            async for message in client.messages:
                now = time.monotonic()
                topic = str(message.topic)
                assert isinstance(message.payload, bytes)
                data = json.loads(message.payload)
                if t_first is None:
                    if topic.endswith("/estimate"):
                        t_first = now
                        t_start = now + WARMUP_S
                        t_end = t_start + seconds
                        next_sample = t_start
                    continue
                if now >= t_end:
                    break
                if now < t_start:
                    continue
                if now >= next_sample:
                    samples.append((now, *_proc_sample(daemon.pid, tick)))
                    next_sample += SAMPLE_PERIOD_S
                if topic.endswith("/estimate"):
                    latencies.append(now - data["t_mono"])
                elif topic.endswith("/measurement"):
                    measurements.append((now, bool(data["fit"]["accepted"])))
                elif topic.endswith("/status") and data.get("rates"):
                    limit = data["rates"].get("depth_limit_hz")
                    if limit:
                        limits.append(float(limit))
    finally:
        with contextlib.suppress(aiomqtt.MqttError):
            await client.__aexit__(None, None, None)
    return _report(
        latencies=latencies, measurements=measurements, limits=limits, samples=samples,
        seconds=seconds, scenario=scenario, mosquitto=mosquitto,
    )  # fmt: skip


def _report(
    *,
    latencies: list[float],
    measurements: list[tuple[float, bool]],
    limits: list[float],
    samples: list[tuple[float, float, int]],
    seconds: float,
    scenario: str,
    mosquitto: bool,
) -> dict[str, Any]:
    lat = sorted(latencies)

    def pct(p: float) -> float | None:
        return 1e3 * lat[min(len(lat) - 1, int(p * len(lat)))] if lat else None

    delay = _sim_capture_delay_s()
    limit = statistics.fmean(limits) if limits else None
    depth_hz = len(measurements) / seconds
    accepted_hz = sum(1 for _, ok in measurements if ok) / seconds
    cpu = None
    rss: dict[str, float] | None = None
    if len(samples) >= 2:
        (t0, c0, _), (t1, c1, _) = samples[0], samples[-1]
        cpu = 100.0 * (c1 - c0) / (t1 - t0)
        values = [r for _, _, r in samples]
        quarter = max(1, len(values) // 4)
        rss = {
            "min_mib": min(values) / 2**20,
            "max_mib": max(values) / 2**20,
            "last_mib": values[-1] / 2**20,
            "growth_first_to_last_quarter_mib": (
                statistics.fmean(values[-quarter:]) - statistics.fmean(values[:quarter])
            )
            / 2**20,
        }
    return {
        "what": (
            f"dffd run (sim camera on a pty, scenario {scenario}, 30 fps, 9600 baud) with "
            f"{'mosquitto' if mosquitto else 'the embedded amqtt broker'} on loopback; "
            f"{seconds:.0f} s measured after {WARMUP_S:.0f} s warm-up"
        ),
        "latency_ms": {"n": len(lat), "p50": pct(0.50), "p99": pct(0.99), "max": pct(1.0)},
        "latency_goal_ms": {"p50": 10.0, "p99": 30.0},
        # The simulated grabber delivers a frame exposure/2 + 1 frame after its mid-exposure
        # (drivers/sim/data/sim-camera.toml); what the daemon itself adds is the rest.
        "capture_delay_ms": None if delay is None else 1e3 * delay,
        "latency_after_delivery_ms": (
            None
            if delay is None or not lat
            else {"p50": pct(0.50) - 1e3 * delay, "p99": pct(0.99) - 1e3 * delay}  # type: ignore[operator]
        ),
        "depth_hz": depth_hz,
        "accepted_depth_hz": accepted_hz,
        "depth_limit_hz": limit,
        "depth_rate_ratio": depth_hz / limit if limit else None,
        "accepted_depth_rate_ratio": accepted_hz / limit if limit else None,
        "depth_rate_goal_ratio": 0.9,
        "cpu_percent_of_one_core": cpu,
        "rss": rss,
    }


def _spawn_daemon(config: Path, work: Path, err: Any) -> subprocess.Popen[bytes]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(  # noqa: S603 - our own interpreter and arguments
        [sys.executable, "-m", "dffd", "run", "--config", str(config), "--no-console"],
        stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=work,
    )  # fmt: skip


def _sim_capture_delay_s() -> float | None:
    """Exposure mid → delivery of the reference simulated camera (exposure/2 + latency)."""
    try:
        from drivers.sim.config import load_sim_camera_config
        from drivers.sim.resources import reference_camera_file

        cfg = load_sim_camera_config(reference_camera_file())
    except (ImportError, ValueError, OSError):
        return None
    cap = cfg.capture
    return 0.5 * cap.exposure_s + cap.capture_latency_frames / cap.fps


def _proc_sample(pid: int, tick: int) -> tuple[float, int]:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu_s = (int(fields[11]) + int(fields[12])) / tick  # utime, stime (fields 14, 15)
    rss_kb = 0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss_kb = int(line.split()[1])
    return cpu_s, rss_kb * 1024


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _start_mosquitto(work: Path, port: int) -> subprocess.Popen[bytes] | None:
    binary = shutil.which("mosquitto") or next(
        (b for b in ("/usr/sbin/mosquitto", "/usr/bin/mosquitto") if Path(b).is_file()), None
    )
    if binary is None:
        return None
    conf = work / "mosquitto.conf"
    conf.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
        "set_tcp_nodelay true\n",
        encoding="utf-8",
    )
    proc = subprocess.Popen(  # noqa: S603 - the system's mosquitto binary
        [binary, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + BROKER_START_TIMEOUT_S
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
            return proc
        time.sleep(PORT_POLL_S)
    proc.kill()
    return None


if __name__ == "__main__":
    sys.exit(main())
