"""What the operator is told about the search sweep: log lines, status block, message, console."""

from __future__ import annotations

import logging

import pytest

from dffd.daemon.console import ConsoleSnapshot, render
from dffd.daemon.searchwatch import SearchWatch
from dffd.daemon.status import StatusBoard
from dffd.mqtt import models
from tests.test_scheduler import Harness
from tests.test_scheduler_search import SEARCH, SMALL

LINK = models.LinkHealth(connected=True)
MQTT = models.MqttHealth(connected=True)
DROPS = models.Drops(frames=0, publish_queue=0, backlog=0, log=0)


def _status(board: StatusBoard, now: float) -> models.Status:
    return board.status(now, depth_limit_hz=2.0, link=LINK, mqtt=MQTT, drops=DROPS)


def test_a_sweep_is_logged_reported_and_shown(caplog: pytest.LogCaptureFixture) -> None:
    h = Harness(SEARCH)
    board = StatusBoard("sim", "lpv", 0.0)
    watch = SearchWatch(h.sched, board)
    h.sched.arm_search(0.0)
    with caplog.at_level(logging.INFO, logger="dffd.daemon.searchwatch"):
        assert watch.update(0.0)  # armed: waiting (a change: the status goes out at once)
        status = _status(board, 0.5)
        assert status.search is not None
        assert status.search.phase == "waiting"
        assert status.search.next_pass_in_s == pytest.approx(SEARCH.search_after_s - 0.5)
        h.run(2.0)
        assert watch.update(h.now)
        assert "search: no target for 1 s of automatic acquisition: sweep 1" in caplog.text
        status = _status(board, h.now)
        assert status.search is not None
        assert status.search.phase == "sweeping"
        assert status.search.view >= 1
        assert "searching: the target is not in view" in (status.message or "")
        assert not watch.update(h.now)  # no change, nothing to log
        snap = board.snapshot(h.now, status, roles={}, pan_tilt_deg=(0.0, 0.0))
        assert snap.search is not None
        assert snap.search.startswith("searching: view")
        text = "".join(seg.text for seg in render(snap).renderables[0].render(_console()))
        assert "(searching: view" in text
        # The target shows: the sweep ends and that is said too.
        h.centroid = (319.5, 239.5)
        h.run(0.5)
        board.state = "tracking"
        assert watch.update(h.now)
        assert "search: target in view after" in caplog.text
        assert _status(board, h.now).search is None


def test_a_fruitless_sweep_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    h = Harness(SMALL)
    board = StatusBoard("sim", "lpv", 0.0)
    watch = SearchWatch(h.sched, board)
    h.sched.arm_search(0.0)
    with caplog.at_level(logging.INFO, logger="dffd.daemon.searchwatch"):
        for _ in range(50):
            h.run(0.1)
            watch.update(h.now)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings, caplog.text
    assert "no target after a whole sweep (8 views" in warnings[0].getMessage()
    assert "next sweep in" in warnings[0].getMessage()
    status = _status(board, h.now)
    assert status.search is not None
    assert status.search.phase in ("holding", "sweeping")


def test_release_says_nothing_of_a_search() -> None:
    h = Harness(SEARCH)
    board = StatusBoard("sim", "lpv", 0.0)
    watch = SearchWatch(h.sched, board)
    h.sched.arm_search(0.0)
    h.run(2.0)
    watch.update(h.now)
    h.sched.stop_pan_tilt()
    board.on_release()
    watch.update(h.now)
    status = _status(board, h.now)
    assert status.search is None
    assert status.message == "released by command: no depths until an acquire command"


def _console() -> object:
    from rich.console import Console

    return Console(width=200)


def test_console_snapshot_without_search_is_unchanged() -> None:
    snap = ConsoleSnapshot(
        camera="sim", state="tracking", uptime_s=1.0, frame_hz=30.0, estimate_hz=30.0,
        depth_hz=2.0, depth_limit_hz=2.0, link_connected=True, link_timeouts=0, link_errors=0,
        link_reconnects=0, mqtt_connected=True, mqtt_backlog=0, frames_dropped=0,
        bursts_accepted=0, bursts_rejected=0,
    )  # fmt: skip
    assert snap.search is None
