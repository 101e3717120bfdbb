"""Real-time mode: the actual daemon, scored over MQTT as a user would see it.

Simulator: ``python -m dffd run`` with ``camera.driver = "sim"`` (the simulated VISCA camera on a
pty, the optics renderer as frame source, ground truth on ``…/sim/truth``), a mosquitto broker
on a free loopback port (the daemon's embedded broker when mosquitto is missing), and this
process subscribed to ``…/estimate``, ``…/measurement``, ``…/status`` and ``…/sim/truth``.
Estimates are matched to truth by the exposure's monotonic time ``t_mono`` (the same frame);
latency is ``time.monotonic()`` at reception minus ``t_mono`` (one machine, one monotonic clock).

Lab: ``--camera serial:PORT --video DEV --truth CSV``: the daemon drives the real camera; the
truth CSV (``t_s,z_m``, any clock) is aligned to the estimates by the time offset that minimises
the RMS difference to the best estimate (see hil/README.md for the procedure).
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import getpass
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dffd.core.tracking3d_types import Track3DEstimate
from hil.baselines import known_size_depth
from hil.results import BurstRecord, RunResult
from hil.runner import RunOptions
from hil.scenario import Scenario
from hil.track3d import Track3DScore, Truth3D

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
# The daemon initialises the camera (Address Set, power, zoom) and starts publishing within a few
# seconds on the simulator; 30 s covers a loaded 2-core machine and a slow real camera.
DAEMON_START_TIMEOUT_S = 30.0
# SIGINT → the daemon publishes offline and exits; it has bounded shutdown steps of ≤ 2 s each.
DAEMON_STOP_TIMEOUT_S = 15.0
# mosquitto accepts connections within milliseconds of exec; 5 s for a loaded machine.
BROKER_START_TIMEOUT_S = 5.0
BROKER_STOP_TIMEOUT_S = 5.0
PORT_POLL_S = 0.02
# MQTT client connection attempt (loopback).
MQTT_CONNECT_TIMEOUT_S = 5.0
# Truth per frame kept for matching estimates (30 fps × 60 s).
TRUTH_HISTORY = 1800
# Lab truth alignment: offsets searched (s) and the step of the coarse grid.
ALIGN_RANGE_S = 5.0
ALIGN_STEP_S = 0.01
# RSS samples of the daemon (one per second) kept for the growth check.
RSS_PERIOD_S = 1.0


@dataclass
class _Collected:
    estimates: list[dict[str, Any]] = field(default_factory=list)
    measurements: list[dict[str, Any]] = field(default_factory=list)
    truth: dict[float, float] = field(default_factory=dict)  # t_mono (rounded) -> z_m
    truth_order: list[float] = field(default_factory=list)
    truth_3d: dict[float, Truth3D] = field(default_factory=dict)  # t_mono (rounded) -> 3D truth
    latency_s: list[float] = field(default_factory=list)
    status: dict[str, Any] | None = None
    first_estimate_at: float | None = None


def run_realtime(scenario: Scenario, options: RunOptions) -> list[RunResult]:
    """Run the daemon for each seed (case: the daemon's built-in world of that name)."""
    lab = options.camera is not None
    seeds = scenario.seeds[:1] if lab else scenario.seeds
    return [asyncio.run(_session(scenario, options, seed)) for seed in seeds]


async def _session(scenario: Scenario, options: RunOptions, seed: int) -> RunResult:
    lab = options.camera is not None
    workdir = Path(tempfile.mkdtemp(prefix="hil-rt-"))
    port = _free_port()
    env = dict(os.environ)
    broker = _start_mosquitto(workdir, port)
    env["DFFD_MQTT__URL"] = f"mqtt://127.0.0.1:{port}" if broker else "embedded"
    if broker is None:
        env["DFFD_MQTT__EMBEDDED_PORT"] = str(port)
    env["DFFD_LOG__DIR"] = str(workdir / "log")
    env["DFFD_MQTT__TOPIC_PREFIX"] = "dffd"
    if lab:
        env.update(_lab_env(options))
    else:
        env["DFFD_CAMERA__DRIVER"] = "sim"
        env["DFFD_CAPTURE__SOURCE"] = "sim"
        env["DFFD_SIM__SCENARIO"] = scenario.name
        env["DFFD_SIM__SEED"] = str(seed)
        env["DFFD_SIM__PUBLISH_TRUTH"] = "true"
    if scenario.target.known_size_m is not None:
        env["DFFD_TARGET__KNOWN_SIZE_M"] = str(scenario.target.known_size_m)
    camera = env.get("DFFD_CAMERA__NAME", "sim")
    cmd = [sys.executable, "-m", "dffd", "run"]
    if options.daemon_config is not None:
        cmd += ["--config", str(options.daemon_config)]
    log_path = workdir / "daemon.log"
    result = RunResult(
        scenario=scenario.name,
        case=scenario.name,
        seed=seed,
        mode="hardware" if lab else "realtime",
        duration_s=scenario.duration_s,
        settle_s=scenario.settle_s,
    )
    if len(scenario.expand()) > 1 and not lab:
        result.notes.append(
            "real-time mode runs the daemon's built-in world for this scenario name "
            "(one case); the lock-step mode runs every case"
        )
    data = _Collected()
    with log_path.open("wb") as log:
        # The daemon is this repository's own CLI run with this interpreter.
        daemon = subprocess.Popen(  # noqa: S603, ASYNC220 - started once, not awaited on
            cmd, cwd=REPO_ROOT, env=env, stdout=log, stderr=log
        )
        try:
            await _collect(daemon, port, camera, scenario, data, result)
        finally:
            _stop(daemon)
            if broker is not None:
                _stop(broker)
    result.extra["daemon_log"] = str(log_path)
    truth_csv = options.truth_csv
    _score(data, result, scenario, truth_csv)
    shutil.rmtree(workdir / "log", ignore_errors=True)
    return result


async def _collect(  # noqa: PLR0917 - private helper of _session
    daemon: subprocess.Popen[bytes],
    port: int,
    camera: str,
    scenario: Scenario,
    data: _Collected,
    result: RunResult,
) -> None:
    import aiomqtt

    base = f"dffd/{camera}"
    deadline = time.monotonic() + DAEMON_START_TIMEOUT_S
    client: aiomqtt.Client | None = None
    while client is None:
        if daemon.poll() is not None:
            raise RuntimeError(
                f"the daemon exited with status {daemon.returncode} before it published; "
                f"see its log ({result.extra.get('daemon_log', 'daemon.log')})"
            )
        try:
            candidate = aiomqtt.Client("127.0.0.1", port, timeout=MQTT_CONNECT_TIMEOUT_S)
            await candidate.__aenter__()
            client = candidate
        except aiomqtt.MqttError:
            if time.monotonic() > deadline:
                raise RuntimeError("no MQTT broker came up for the daemon") from None
            await asyncio.sleep(0.2)
    try:
        for leaf in ("estimate", "measurement", "status", "sim/truth"):
            await client.subscribe(f"{base}/{leaf}")
        started = time.monotonic()
        cpu0: tuple[float, float] | None = None
        rss: list[int] = []
        next_rss = started
        async with asyncio.timeout(DAEMON_START_TIMEOUT_S + scenario.duration_s + 10.0):
            async for message in client.messages:
                now = time.monotonic()
                topic = message.topic.value
                payload = json.loads(bytes(message.payload))
                if topic.endswith("/sim/truth"):
                    key = round(float(payload["t_mono"]), 4)
                    data.truth[key] = float(payload["z_m"])
                    data.truth_order.append(key)
                    truth3d = _truth_3d(payload)
                    if truth3d is not None:
                        data.truth_3d[key] = truth3d
                    if len(data.truth_order) > TRUTH_HISTORY * 4:
                        for old in data.truth_order[:TRUTH_HISTORY]:
                            data.truth.pop(old, None)
                            data.truth_3d.pop(old, None)
                        del data.truth_order[:TRUTH_HISTORY]
                elif topic.endswith("/estimate"):
                    if data.first_estimate_at is None:
                        data.first_estimate_at = now
                        cpu0 = _cpu_times(daemon.pid)
                    if not payload.get("replayed"):
                        data.latency_s.append(now - float(payload["t_mono"]))
                    data.estimates.append(payload)
                elif topic.endswith("/measurement"):
                    data.measurements.append(payload)
                elif topic.endswith("/status"):
                    data.status = payload
                if data.first_estimate_at is not None and now >= next_rss:
                    rss.append(_rss_kib(daemon.pid))
                    next_rss = now + RSS_PERIOD_S
                if (
                    data.first_estimate_at is not None
                    and now - data.first_estimate_at >= scenario.duration_s
                ):
                    break
                if now - started > DAEMON_START_TIMEOUT_S and data.first_estimate_at is None:
                    raise RuntimeError("the daemon published no estimate; see its log")
        cpu1 = _cpu_times(daemon.pid)
        if cpu0 is not None and data.first_estimate_at is not None:
            wall = time.monotonic() - data.first_estimate_at
            result.extra["daemon_cpu_fraction"] = (sum(cpu1) - sum(cpu0)) / wall
            result.wall_s = wall
        result.extra["daemon_rss_kib"] = rss
    finally:
        with contextlib.suppress(Exception):
            await client.__aexit__(None, None, None)


def _score(data: _Collected, result: RunResult, scenario: Scenario, truth_csv: Path | None) -> None:
    lab_truth = _load_truth_csv(truth_csv) if truth_csv is not None else None
    est = data.estimates
    if not est:
        result.notes.append("no estimates received")
        return
    t0 = float(est[0]["t_mono"])
    result.t_start = t0
    offset = 0.0
    if lab_truth is not None:
        offset = _align(est, lab_truth)
        result.extra["truth_offset_s"] = offset

    if lab_truth is None:
        keys = sorted(data.truth)
        sim_t = np.asarray(keys)
        sim_z = np.asarray([data.truth[k] for k in keys])

    def truth_at(t: float) -> float:
        if lab_truth is not None:
            tt, zz = lab_truth
            return float(np.interp(t + offset, tt, zz, left=math.nan, right=math.nan))
        exact = data.truth.get(round(t, 4))
        if exact is not None:
            return exact
        # A burst's time is not a frame time: interpolate between the frames around it.
        if sim_t.size < 2 or not sim_t[0] <= t <= sim_t[-1]:
            return math.nan
        return float(np.interp(t, sim_t, sim_z))

    size = scenario.target.known_size_m
    lens = _lens_for(scenario)
    for p in est:
        t = float(p["t_mono"])
        tz = truth_at(t)
        sigmas = p.get("sigmas_m") or {}
        for name, z in (p.get("depth_m") or {}).items():
            if name == "measured" or z is None:
                continue
            result.series(name).add(t, float(z), tz, sigmas.get(name))
        if p.get("beta_m_s") is not None:
            result.beta.add(t, float(p["beta_m_s"]))
        if p.get("size_m") is not None:
            result.size.add(t, float(p["size_m"]), scenario.target.size_m)
        r = p.get("r_px")
        if size is not None and lens is not None and r:
            z_ks = known_size_depth(float(r), size, lens.focal_length_mm, lens.pixel_pitch_mm)
            result.baseline("known_size").add(t, z_ks, tz)
        result.frames += 1
    accepted = 0
    for m in data.measurements:
        t = float(m["t_mono"])
        fit = m.get("fit") or {}
        if fit.get("accepted") and m.get("z_m") is not None:
            accepted += 1
            result.series("measured").add(t, float(m["z_m"]), truth_at(t))
    for m in data.measurements:
        fit = m.get("fit") or {}
        v = m.get("v_mm") or []
        result.bursts.append(
            BurstRecord(
                t=float(m["t_mono"]),
                v0_mm=tuple(float(x) for x in v),
                cost=tuple(float(x) for x in m.get("costs") or ()),
                accepted=bool(fit.get("accepted")),
                reason=str(fit.get("reason") or ""),
                v_hat_mm=fit.get("v_mm"),
                coeffs=None,
                z_m=m.get("z_m"),
                truth_z_m=truth_at(float(m["t_mono"])),
                truth_v_mm=None,
            )
        )
    if lab_truth is None:
        result.track3d = _score_3d(est, data.truth_3d, scenario.settle_s, t0)
    result.latency_s = data.latency_s
    if lab_truth is None:
        result.extra["latency_note"] = (
            "exposure → subscriber; includes the simulated capture chain's delivery lag "
            "(exposure/2 + capture_latency_frames/fps)"
        )
    result.duration_s = max(float(est[-1]["t_mono"]) - t0, 1e-9)
    rates = (data.status or {}).get("rates") or {}
    result.depth_limit_hz = rates.get("depth_limit_hz")
    result.extra["status_rates"] = rates
    result.extra["accepted_measurements"] = accepted
    matched = [np.isfinite(s.arrays()[2]).any() for s in result.estimates.values() if len(s)]
    if not any(matched):
        result.notes.append("no estimate could be matched to ground truth")


def _truth_3d(payload: dict[str, Any]) -> Truth3D | None:
    """The 3D truth of a ``…/sim/truth`` payload (None from a simulator without it)."""
    vel, acc = payload.get("velocity_m_s"), payload.get("acceleration_m_s2")
    omega = payload.get("angular_speed_rad_s")
    if vel is None or acc is None or omega is None:
        return None
    pos = payload["position_m"]
    return Truth3D(
        (float(pos[0]), float(pos[1]), float(pos[2])),
        (float(vel[0]), float(vel[1]), float(vel[2])),
        (float(acc[0]), float(acc[1]), float(acc[2])),
        float(omega),
    )


def _score_3d(
    estimates: list[dict[str, Any]], truth: dict[float, Truth3D], settle_s: float, t0: float
) -> Track3DScore | None:
    """The published 3D track (the daemon's MMAE) of every estimate that carries one, against
    the 3D truth of its frame; None when no estimate could be matched."""
    score = Track3DScore(settle_s)
    matched = 0
    for p in estimates:
        sigma = p.get("position_sigma_m")
        t = float(p["t_mono"])
        tr = truth.get(round(t, 4))
        if sigma is None or tr is None or p.get("acceleration_m_s2") is None:
            continue
        est = Track3DEstimate(
            t=t,
            position_m=_vec3(p["position_m"]),
            velocity_m_s=_vec3(p["velocity_m_s"]),
            acceleration_m_s2=_vec3(p["acceleration_m_s2"]),
            angular_speed_rad_s=float(p.get("angular_speed_rad_s") or 0.0),
            position_sigma_m=_vec3(sigma),
            model_probabilities=dict(p.get("model_probabilities") or {}),
        )
        score.add(t - t0, tr, {"mmae": est})
        matched += 1
    return score if matched else None


def _vec3(v: Any) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _lens_for(scenario: Scenario) -> Any:
    from dffd.core.lens import Lens, LensError
    from hil.simbuild import lens_file

    path = lens_file(scenario.camera.lens)
    try:
        return Lens.from_toml(path)
    except LensError:
        return None


def _load_truth_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ValueError(f"cannot read truth CSV {path}: {exc}") from exc
    if not rows or "t_s" not in rows[0] or "z_m" not in rows[0]:
        raise ValueError(f"truth CSV {path} needs a header with t_s and z_m columns")
    t = np.asarray([float(r["t_s"]) for r in rows])
    z = np.asarray([float(r["z_m"]) for r in rows])
    order = np.argsort(t)
    return t[order], z[order]


def _align(estimates: list[dict[str, Any]], truth: tuple[np.ndarray, np.ndarray]) -> float:
    """Offset (s) to add to the daemon's t_mono to read the truth CSV's clock.

    First the offset of the two clocks' origins (first samples), then a grid search of
    ±ALIGN_RANGE_S around it minimising the RMS of best-estimate − truth.
    """
    tt, zz = truth
    t_est = np.asarray([float(p["t_mono"]) for p in estimates])
    z_est = np.asarray([np.nan if p.get("z_m") is None else float(p["z_m"]) for p in estimates])
    ok = np.isfinite(z_est)
    t_est, z_est = t_est[ok], z_est[ok]
    if t_est.size == 0:
        return float(tt[0] - 0.0)
    base = float(tt[0] - t_est[0])
    best, best_rms = base, math.inf
    for off in np.arange(base - ALIGN_RANGE_S, base + ALIGN_RANGE_S, ALIGN_STEP_S):
        z_true = np.interp(t_est + off, tt, zz, left=np.nan, right=np.nan)
        err = z_est - z_true
        err = err[np.isfinite(err)]
        if err.size < 10:
            continue
        rms = float(np.sqrt(np.mean(err**2)))
        if rms < best_rms:
            best, best_rms = float(off), rms
    return best


def _lab_env(options: RunOptions) -> dict[str, str]:
    camera = options.camera or ""
    if not camera.startswith("serial:"):
        raise ValueError(f"--camera {camera!r}: expected serial:PORT, e.g. serial:/dev/ttyUSB0")
    return {
        "DFFD_CAMERA__DRIVER": "visca",
        "DFFD_CAMERA__PORT": camera.removeprefix("serial:"),
        "DFFD_CAPTURE__SOURCE": "v4l2",
        "DFFD_CAPTURE__DEVICE": options.video or "",
    }


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_mosquitto(workdir: Path, port: int) -> subprocess.Popen[bytes] | None:
    binary = shutil.which("mosquitto") or next(
        (c for c in ("/usr/sbin/mosquitto", "/usr/bin/mosquitto") if Path(c).is_file()), None
    )
    if binary is None:
        return None
    conf = workdir / "mosquitto.conf"
    conf.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
        f"user {getpass.getuser()}\nset_tcp_nodelay true\n",
        encoding="utf-8",
    )
    log = (workdir / "mosquitto.log").open("wb")
    proc = subprocess.Popen([binary, "-c", str(conf)], stdout=log, stderr=log)  # noqa: S603
    log.close()
    deadline = time.monotonic() + BROKER_START_TIMEOUT_S
    while True:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
            return proc
        if time.monotonic() > deadline or proc.poll() is not None:
            _stop(proc)
            return None
        time.sleep(PORT_POLL_S)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(DAEMON_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(BROKER_STOP_TIMEOUT_S)


def _cpu_times(pid: int) -> tuple[float, float]:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return (0.0, 0.0)
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


def _rss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0
