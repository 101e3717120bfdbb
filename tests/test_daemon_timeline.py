"""The start-up timeline of ``dffd run`` (dffd.daemon.timeline): steps on the process's clock."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys
import time
from contextlib import suppress
from pathlib import Path

import pytest

from dffd.daemon.timeline import StartTimeline, process_start_monotonic
from tests.conftest import free_port

# Interpreter start, imports and the embedded broker on a loaded 2-core machine: a few seconds
# (as tests/test_daemon_default.py).
BROKER_UP_TIMEOUT_S = 20.0
# The daemon's shutdown bound is 10 s (dffd.daemon.app.SHUTDOWN_TIMEOUT_S).
EXIT_TIMEOUT_S = 12.0
# Safety net: the daemon stops by itself after this long even if the test dies.
RUN_DURATION_S = 60.0
BROKER_LINE = b"embedded MQTT broker listening"
# The first step, marked when the daemon is built: before the broker starts.
FIRST_STEP_LINE = b"DEBUG dffd.daemon.timeline: start-up "


def test_the_process_start_lies_before_now_and_after_the_interpreter_began() -> None:
    # This test's process started before its first test ran and less than a day ago; the
    # estimate comes from /proc (clock ticks), not from the first call.
    now = time.monotonic()
    start = process_start_monotonic()
    assert now - 86400.0 < start < now - 0.01


def test_each_step_is_logged_once_with_its_time_since_the_process_start(
    caplog: pytest.LogCaptureFixture,
) -> None:
    timeline = StartTimeline()
    with caplog.at_level(logging.DEBUG, logger="dffd.daemon.timeline"):
        timeline.mark("camera initialised")
        timeline.mark("camera initialised")
        timeline.event("burst closed")
        timeline.event("burst closed")
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3
    assert timeline.marked("camera initialised")
    assert not timeline.marked("first depth published")
    assert messages[0].startswith("start-up ")
    assert messages[0].endswith(" s: camera initialised")
    seconds = float(messages[0].split()[1])
    # logged to the millisecond (%.3f): it may read up to 0.5 ms above the elapsed time
    assert 0.01 < seconds <= time.monotonic() - timeline.t0 + 0.0005


@pytest.mark.slow
@pytest.mark.timeout(60)
async def test_dash_vv_shows_the_timeline_over_the_configured_level(tmp_path: Path) -> None:
    """``dffd -vv run`` logs the start-up steps although ``[log] level`` is INFO (the default):
    the command line's verbosity wins when it asks for more."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(
        PYTHONUNBUFFERED="1",
        DFFD_MQTT__EMBEDDED_PORT=str(free_port()),
        DFFD_WEB__LISTEN=f"127.0.0.1:{free_port()}",
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "dffd", "-vv", "run", "--no-console",
        "--duration", str(RUN_DURATION_S), cwd=tmp_path, env=env,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stderr is not None
    log: list[bytes] = []
    try:
        async with asyncio.timeout(BROKER_UP_TIMEOUT_S):
            async for line in proc.stderr:
                log.append(line)
                if BROKER_LINE in line:
                    break
        assert any(BROKER_LINE in line for line in log), b"".join(log)[-3000:]
        # logged when the daemon was built, before the broker came up
        assert any(FIRST_STEP_LINE in line for line in log), b"".join(log)[-3000:]
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(EXIT_TIMEOUT_S):
            await proc.stderr.read()  # drain, or a full pipe would block its shutdown
            code = await proc.wait()
        assert code == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            with suppress(ProcessLookupError):
                await proc.wait()
