"""The search sweep on the live daemon: ``python -m dffd run`` with the simulated camera on the
embedded default's world (the paper-like circle from its far point, moving) and a real mosquitto.

Release, wait until the simulator's truth says the target has left the field of view, then
``acquire`` without an ROI: the core finds nothing in view, the head sweeps, finds the target and
estimates flow again within a bounded time.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import Mosquitto
from tests.test_daemon_e2e import (
    EXIT_TIMEOUT_S,
    MESSAGE_TIMEOUT_S,
    STARTUP_TIMEOUT_S,
    DaemonProcess,
    online,
    subscribe,
    write_config,
)

pytestmark = pytest.mark.slow

# After a release at the far point (10 m) the target crosses at 0.25 m/s / 10 m = 1.4°/s, and a
# ±3° field of view: its outline leaves the frame 2-3 s after the head stopped.
OUT_OF_VIEW_TIMEOUT_S = 20.0
# Acquire → estimates again: search_after_s (3 s) of whole-frame search, then the sweep's first
# views (~0.4 s each: a move and a 0.3 s dwell) on the start's row, where the target is (a few
# views away); ~6 s on an idle machine, generous for the loaded 2-core one.
REACQUIRE_TIMEOUT_S = 30.0


def moving_config(tmp_path: Path, broker: Mosquitto) -> Path:
    """The e2e config on the embedded default's world: the paper-like circle from 180°."""
    path = write_config(tmp_path, broker)
    text = path.read_text(encoding="utf-8").replace(
        'scenario = "static"', 'scenario = "paper-circle"\nstart_phase_deg = 180.0'
    )
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.timeout(120)
async def test_acquire_after_the_target_left_the_view_sweeps_and_finds_it(
    tmp_path: Path, mosquitto: Mosquitto
) -> None:
    daemon = DaemonProcess(tmp_path, moving_config(tmp_path, mosquitto))
    try:
        async with subscribe(mosquitto) as sub:
            await sub.wait_for(online, STARTUP_TIMEOUT_S)
            await sub.wait_for(lambda m: len(m["estimate"]) >= 20, MESSAGE_TIMEOUT_S)
            release = await sub.command(b'{"cmd": "release", "id": "r"}', "r")
            assert release["ok"] is True, release
            truths = len(sub.messages["sim/truth"])
            # The head stopped; the target moves on until the truth says it is out of view.
            await sub.wait_for(
                lambda m: any(t.get("in_view") is False for t in m["sim/truth"][truths:]),
                OUT_OF_VIEW_TIMEOUT_S,
            )
            n_estimates = len(sub.messages["estimate"])
            n_status = len(sub.messages["status"])
            n_truths = len(sub.messages["sim/truth"])
            t0 = time.monotonic()
            acquire = await sub.command(b'{"cmd": "acquire", "id": "a"}', "a")
            assert acquire["ok"] is True, acquire
            assert not _in_view(sub.messages["sim/truth"][-1])  # still out of view
            await sub.wait_for(lambda m: len(m["estimate"]) > n_estimates + 10, REACQUIRE_TIMEOUT_S)
            found_s = time.monotonic() - t0
            assert found_s < REACQUIRE_TIMEOUT_S
            # It was the sweep: the status said so while it ran, and the log tells the story.
            statuses = sub.messages["status"][n_status:]
            sweeping = [s for s in statuses if (s.get("search") or {}).get("phase") == "sweeping"]
            assert sweeping, [s.get("search") for s in statuses]
            assert "searching" in (sweeping[-1].get("message") or "")
            assert sweeping[-1]["state"] in ("acquiring", "lost")
            log = daemon.log()
            assert "search: no target for 3 s of automatic acquisition" in log
            assert "search: target in view after" in log
            # Back in view, tracked, and the search block gone.
            assert any(_in_view(t) for t in sub.messages["sim/truth"][n_truths:])
            await sub.wait_for(
                lambda m: (
                    m["status"][-1].get("state") == "tracking"
                    and m["status"][-1].get("search") is None
                ),
                MESSAGE_TIMEOUT_S,
            )
            assert sub.invalid == []
        code, elapsed = daemon.terminate()
        assert code == 0, daemon.log()
        assert elapsed < EXIT_TIMEOUT_S
    finally:
        daemon.kill()


def _in_view(truth: dict[str, Any]) -> bool:
    return bool(truth.get("in_view"))
