"""The README run path: ``dffd run`` with no config file produces depth estimates within seconds.

What ``make run`` does — simulated camera over a pty, the paper-like circle, the embedded amqtt
broker — only with ``--no-console`` and the embedded broker moved to a free port through
``DFFD_MQTT__EMBEDDED_PORT`` (the one documented override). The test waits on events with
timeouts: the daemon's own log line that the broker listens, then MQTT messages.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import sys
from contextlib import suppress
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from tests.conftest import free_port

pytestmark = pytest.mark.slow

# Interpreter start, imports and the embedded broker on a loaded 2-core machine: a few seconds.
BROKER_UP_TIMEOUT_S = 20.0
# From the broker being up to the first estimate with a depth: camera init (~0.2 s), focus to
# the start depth and acquisition (~1 s), the first burst spanning the range (~2 s) — issue 5
# asks for "within seconds"; 15 s leaves room for a loaded CI machine.
FIRST_DEPTH_TIMEOUT_S = 15.0
# The first published depth against the truth, in its own σ: measured 0.1-0.8σ over five runs
# (0.03-0.36 m at σ 0.34-0.47 m, 2.1-3.0 m at σ 4-5 m); the extrapolated first burst published
# before was 6-7σ off. 3σ: a 1-in-370 event for an honest Gaussian σ.
FIRST_DEPTH_SIGMAS = 3.0
# An estimate with σ below this claims its depth to within the working range's scale.
CONFIDENT_SIGMA_M = 1.0
# Estimates with a depth to collect before the run counts as producing estimates.
DEPTH_ESTIMATES = 10
# The daemon's shutdown bound is 10 s (dffd.daemon.app.SHUTDOWN_TIMEOUT_S).
EXIT_TIMEOUT_S = 12.0
# Safety net: the daemon stops by itself after this long even if the test dies.
RUN_DURATION_S = 60.0
BROKER_LINE = b"embedded MQTT broker listening"


@pytest.mark.timeout(90)
async def test_default_run_produces_estimates_within_seconds(tmp_path: Path) -> None:
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(PYTHONUNBUFFERED="1", DFFD_MQTT__EMBEDDED_PORT=str(port))
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "dffd", "run", "--no-console", "--duration", str(RUN_DURATION_S),
        cwd=tmp_path, env=env, stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stderr is not None
    log: list[bytes] = []
    broker_up = asyncio.Event()

    async def drain(stream: asyncio.StreamReader) -> None:
        async for line in stream:
            log.append(line)
            if BROKER_LINE in line:
                broker_up.set()

    drainer = asyncio.create_task(drain(proc.stderr))
    try:
        async with asyncio.timeout(BROKER_UP_TIMEOUT_S):
            await broker_up.wait()
        depths: list[dict[str, Any]] = []
        truth: list[dict[str, Any]] = []
        async with aiomqtt.Client("127.0.0.1", port) as client:
            await client.subscribe("dffd/sim/estimate", qos=0)
            await client.subscribe("dffd/sim/sim/truth", qos=0)
            async with asyncio.timeout(FIRST_DEPTH_TIMEOUT_S):
                async for message in client.messages:
                    assert isinstance(message.payload, bytes)
                    payload = json.loads(message.payload)
                    if message.topic.matches("dffd/sim/sim/truth"):
                        truth.append(payload)
                    elif payload["z_m"] is not None:
                        depths.append(payload)
                    # Estimates come on every frame (30/s): ten depths arrive within a third of
                    # a second of the first, before a second burst can tighten σ; wait for one
                    # confident estimate too.
                    confident_seen = any(p["sigma_m"] < CONFIDENT_SIGMA_M for p in depths)
                    if len(depths) >= DEPTH_ESTIMATES and confident_seen:
                        break
        assert all(p["state"] == "tracking" for p in depths)
        # The demo starts the circle at its far point (sim.start_phase_deg = 180: 10 m); the
        # estimates that claim to know bracket it within the working range (accuracy is the
        # bench's job). A first depth from a burst spanning most of the focus range can be far
        # off (12-35 m seen) and says so with its σ (4-5 m): checked against that σ below.
        assert all(math.isfinite(p["z_m"]) and math.isfinite(p["sigma_m"]) for p in depths)
        confident = [p for p in depths if p["sigma_m"] < CONFIDENT_SIGMA_M]
        assert confident, depths
        assert all(2.0 < p["z_m"] < 20.0 for p in confident)
        # The first published depth is honest: no depth from the first, extrapolated burst (it
        # put the target at 13-16 m while it was at 10 m, published with σ 0.75 m: 6-7σ); a
        # burst that brackets its vertex but spans most of the focus range is still biased
        # (12-13 m), and is published with the σ that says so (issue 13).
        first = depths[0]
        true_z = min(truth, key=lambda p: abs(p["t_mono"] - first["t_mono"]))["z_m"]
        error = abs(first["z_m"] - true_z)
        assert error < FIRST_DEPTH_SIGMAS * first["sigma_m"], (first, true_z)
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(EXIT_TIMEOUT_S):
            code = await proc.wait()
        assert code == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        drainer.cancel()
        with suppress(asyncio.CancelledError):
            await drainer
        text = b"".join(log).decode(errors="replace")
        print(text[-4000:])
    assert b"target lost" not in b"".join(log)
