"""The start-up timeline of ``dffd run`` (dffd.daemon.timeline): steps on the process's clock."""

from __future__ import annotations

import logging
import time

import pytest

from dffd.daemon.timeline import StartTimeline, process_start_monotonic


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
