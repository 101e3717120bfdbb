"""The daemon's console view: what it says about each depth, and log lines above the live view."""

from __future__ import annotations

import io
import logging
import sys
from dataclasses import replace

import pytest
from rich.console import Console as RichConsole

from dffd.daemon.console import CF1_NEEDS_SIZE, Console, ConsoleSnapshot, render

SNAP = ConsoleSnapshot(
    camera="sim", state="tracking", uptime_s=10.0, frame_hz=30.0, estimate_hz=10.0,
    depth_hz=2.0, depth_limit_hz=2.3, link_connected=True, link_timeouts=0, link_errors=0,
    link_reconnects=0, mqtt_connected=True, mqtt_backlog=0, frames_dropped=0,
    bursts_accepted=3, bursts_rejected=0,
    depth_m={"measured": 4.02, "cf1": None, "cf2": 4.01, "lpv": 4.0, "kf": 4.0},
    last_estimate_age_s=0.04, truth_z_m=4.0, measured_age_s=0.4,
)  # fmt: skip


def text_of(snap: ConsoleSnapshot) -> str:
    console = RichConsole(record=True, width=160)
    console.print(render(snap))
    return console.export_text()


def test_cf1_says_what_it_needs_instead_of_a_bare_dash() -> None:
    assert CF1_NEEDS_SIZE in text_of(SNAP)
    known = replace(SNAP, known_size_m=0.0358, depth_m={**SNAP.depth_m, "cf1": 3.99})
    assert CF1_NEEDS_SIZE not in text_of(known)
    assert "3.990" in text_of(known)


def test_the_age_of_the_last_estimate_and_measurement_is_shown() -> None:
    text = text_of(SNAP)
    assert "last estimate 0.0 s ago" in text
    assert "measured (0.4 s ago)" in text
    assert "last estimate 2.5 s ago" in text_of(replace(SNAP, last_estimate_age_s=2.5))
    assert "none since start or release" in text_of(replace(SNAP, last_estimate_age_s=None))


def test_log_records_go_through_the_live_view_and_the_handler_comes_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    root = logging.getLogger()
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)  # the terminal, as logging.basicConfig sees it
    original = logging.StreamHandler()
    original.setFormatter(logging.Formatter("LOG %(message)s"))
    saved = root.handlers[:]
    root.handlers = [original]
    screen = io.StringIO()
    terminal = RichConsole(file=screen, force_terminal=True, width=120, color_system=None)
    try:
        with Console(live=True, terminal=terminal) as console:
            logging.getLogger("dffd.test").warning("camera on /dev/pts/9")
            console.update(SNAP)
            assert original not in root.handlers
        console.farewell("dffd stopped cleanly")
        assert root.handlers == [original]
        logging.getLogger("dffd.test").warning("after")
    finally:
        root.handlers = saved
    # While the view was up the record was drawn by rich (which keeps the view below it), not
    # written behind its back to the terminal; the handler's own format was kept.
    assert "LOG camera on /dev/pts/9" in screen.getvalue()
    assert "dffd stopped cleanly" in screen.getvalue()
    assert stream.getvalue() == "LOG after\n"


def test_an_acquire_says_what_it_searches_until_the_target_is_tracked() -> None:
    from dffd.daemon.status import StatusBoard

    board = StatusBoard("sim", "lpv", 0.0)
    board.on_release()
    assert "released" in (board.message or "")
    board.on_acquire(None)
    assert board.state == "acquiring"
    assert "searching the whole frame" in (board.message or "")
    board.on_acquire((10, 20, 100, 80))
    assert "roi [10, 20, 100, 80]" in (board.message or "")
