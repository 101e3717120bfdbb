"""Start → first estimate and → first depth of ``dffd run`` on its embedded default (issue 13.4).

Starts ``dffd run --no-console`` the way ``make run`` does — simulated camera, embedded broker, no
configuration — with only the broker's and the dashboard's ports moved to free ones
(``DFFD_MQTT__EMBEDDED_PORT``, ``DFFD_WEB__LISTEN``), subscribes to ``dffd/+/estimate`` and the
simulator's truth, and times from the process start to the first estimate and to the first
estimate that carries a depth (``z_m`` not null), with that depth's error against the truth of
the same frame. ``--fresh-kernel-cache`` gives the daemon an empty ``NUMBA_CACHE_DIR``.

    python -m hil.bench_start [--repeat 3] [--fresh-kernel-cache] [--out bench_start.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hil.realtime import MQTT_CONNECT_TIMEOUT_S, REPO_ROOT
from hil.realtime import _free_port as free_port
from hil.realtime import _stop as stop_process

__all__ = ["main", "measure_start"]

# A start with the kernels cached gives its first depth in 3-15 s (idle to a loaded 2-core
# machine); a daemon without one after this long is a failure, reported as such.
FIRST_DEPTH_TIMEOUT_S = 90.0
# The broker connection is retried this often while the daemon starts.
CONNECT_RETRY_S = 0.1
# Frame truths kept to match the first depth's frame (2 s at 30 fps).
TRUTHS_KEPT = 60


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``--repeat`` starts, print each and the medians, write JSON to ``--out``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="starts to time")
    parser.add_argument("--fresh-kernel-cache", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="JSON result file")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    runs = []
    load_before = list(os.getloadavg())
    print(f"load average {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f}")
    for _ in range(args.repeat):
        run = measure_start(fresh_kernel_cache=args.fresh_kernel_cache)
        runs.append(run)
        print(
            f"first estimate {_s(run['first_estimate_s'])} s, first depth "
            f"{_s(run['first_depth_s'])} s (z {_s(run['first_depth_m'])} m, truth "
            f"{_s(run['first_depth_truth_m'])} m){' ' + run['error'] if run['error'] else ''}"
        )
        # where the time between them went: each burst the core closed, when and how it fitted
        for t, what in run["events"]:
            if what.startswith("burst"):
                print(f"  {t:6.2f} s  {what}")
    result: dict[str, Any] = {
        "repeat": args.repeat,
        "fresh_kernel_cache": args.fresh_kernel_cache,
        "runs": runs,
        "load_average_before": load_before,
        "load_average": list(os.getloadavg()),
    }
    for key in ("first_estimate_s", "first_depth_s"):
        values = [r[key] for r in runs if r[key] is not None]
        result[f"median_{key}"] = statistics.median(values) if values else None
        result[f"max_{key}"] = max(values) if values else None
    print(
        f"median: first estimate {_s(result['median_first_estimate_s'])} s, first depth "
        f"{_s(result['median_first_depth_s'])} s over {args.repeat} starts"
    )
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


def measure_start(*, fresh_kernel_cache: bool = False) -> dict[str, Any]:
    """One start of ``dffd run --no-console`` on the embedded default, timed to its first depth."""
    import subprocess

    work = Path(tempfile.mkdtemp(prefix="hil-start-"))
    port = free_port()
    env = dict(os.environ)
    env.update(
        {
            "DFFD_MQTT__EMBEDDED_PORT": str(port),
            "DFFD_WEB__LISTEN": f"127.0.0.1:{free_port()}",
            "DFFD_LOG__DIR": str(work / "log"),
        }
    )
    if fresh_kernel_cache:
        env["NUMBA_CACHE_DIR"] = str(work / "numba-cache")
    run: dict[str, Any] = {
        "first_estimate_s": None,
        "first_depth_s": None,
        "first_depth_m": None,
        "first_depth_truth_m": None,
        "error": None,
        # what led to the first depth: (s after start, event) for states and bursts
        "events": [],
    }
    t0 = time.monotonic()
    with (work / "daemon.log").open("wb") as log:
        daemon = subprocess.Popen(
            [sys.executable, "-m", "dffd", "run", "--no-console"],
            cwd=REPO_ROOT,
            env=env,
            stdout=log,
            stderr=log,
        )
        try:
            asyncio.run(_watch(daemon, port, t0, run))
        except (TimeoutError, RuntimeError) as exc:
            run["error"] = f"{type(exc).__name__}: {exc} (see {work / 'daemon.log'})"
        finally:
            stop_process(daemon)
    if run["error"] is None:
        # the daemon's log and caches are only worth keeping when the start failed (the error
        # names the log); a good start's would pile up in /tmp, one directory a start
        shutil.rmtree(work, ignore_errors=True)
    return run


async def _watch(daemon: Any, port: int, t0: float, run: dict[str, Any]) -> None:
    import aiomqtt

    async with asyncio.timeout(FIRST_DEPTH_TIMEOUT_S):
        while True:
            if daemon.poll() is not None:
                raise RuntimeError(f"the daemon exited with status {daemon.returncode}")
            try:
                async with aiomqtt.Client(
                    "127.0.0.1", port, timeout=MQTT_CONNECT_TIMEOUT_S
                ) as client:
                    await client.subscribe("dffd/+/estimate")
                    await client.subscribe("dffd/+/sim/truth")
                    await client.subscribe("dffd/+/measurement")
                    await client.subscribe("dffd/+/status")
                    await _receive(client, t0, run)
                    return
            except aiomqtt.MqttError:
                await asyncio.sleep(CONNECT_RETRY_S)


async def _receive(client: Any, t0: float, run: dict[str, Any]) -> None:
    truths: dict[float, float] = {}
    async for message in client.messages:
        now = time.monotonic() - t0
        payload = json.loads(bytes(message.payload))
        topic = message.topic.value
        if topic.endswith("/status"):
            state = payload.get("state")
            if not run["events"] or run["events"][-1][1] != f"state {state}":
                run["events"].append((round(now, 3), f"state {state}"))
            continue
        if topic.endswith("/measurement"):
            fit = payload.get("fit") or {}
            verdict = fit.get("reason") or ("accepted" if fit.get("accepted") else "")
            what = f"burst {payload.get('focus_counts')} z {payload.get('z_m')} {verdict}"
            run["events"].append((round(now, 3), what))
            continue
        if topic.endswith("/sim/truth"):
            truths[float(payload["t_mono"])] = float(payload["z_m"])
            if len(truths) > TRUTHS_KEPT:
                del truths[next(iter(truths))]
            continue
        if run["first_estimate_s"] is None:
            run["first_estimate_s"] = now
        if payload.get("z_m") is not None:
            run["first_depth_s"] = now
            run["first_depth_m"] = float(payload["z_m"])
            run["first_depth_truth_m"] = truths.get(float(payload["t_mono"]))
            return


def _s(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


if __name__ == "__main__":
    sys.exit(main())
