"""The search sweep: views over the head's range, driven by the pure scheduler (no clock).

The scheduler runs against the discrete-event camera model of tests/test_scheduler.py: frames
without a centroid until the test says the target shows.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import pytest

from dffd.scheduler import (
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltStop,
    Scheduler,
    search_views,
)
from dffd.scheduler.search import view_step_deg
from drivers.visca.camera import EVI_D100
from tests.test_scheduler import PT, Harness, _pan_tilt_commands

# The reference camera's head and lens (f = 31 mm, 5 µm pixels: a 5.9° x 4.4° field of view).
SEARCH = replace(
    PT,
    focal_length_mm=31.0,
    pixel_pitch_mm=0.005,
    pan_tilt_poll_interval_s=100.0,  # no inquiries: the model camera answers them with (0, 0)
    search_after_s=1.0,
    search_retry_s=5.0,
    search_dwell_s=0.3,
    pan_range_deg=EVI_D100.pan_range_deg,
    tilt_range_deg=EVI_D100.tilt_range_deg,
    initial_focus_counts=5000,
)
# A small head (3 x 3 views): a whole pass fits a short test.
SMALL = replace(SEARCH, pan_range_deg=(-4.0, 4.0), tilt_range_deg=(-3.0, 3.0))


def test_the_views_cover_the_range_once_nearest_row_first() -> None:
    step = view_step_deg(SEARCH)
    assert step[0] == pytest.approx(0.8 * 2 * math.degrees(math.atan(1.6 / 31.0)))
    views = search_views((10.0, 2.0), (-100.0, 100.0), (-25.0, 25.0), step)
    assert len(views) == len(set(views))
    assert (10.0, 2.0) not in views  # the start is where the core has looked already
    pans = sorted({p for p, _ in views} | {10.0})
    tilts = sorted({t for _, t in views} | {2.0})
    assert pans[0] == -100.0
    assert pans[-1] == 100.0
    assert tilts[0] == -25.0
    assert tilts[-1] == 25.0
    assert max(b - a for a, b in itertools.pairwise(pans)) <= step[0] + 1e-9
    assert max(b - a for a, b in itertools.pairwise(tilts)) <= step[1] + 1e-9
    assert len(views) == len(pans) * len(tilts) - 1  # every grid view, once
    # The start's row first, its nearest views first (zig-zag: +1, -1, -2, +2 … views).
    row = [p for p, t in views if t == 2.0]
    assert views[: len(row)] == [(p, 2.0) for p in row]
    assert [round((p - 10.0) / step[0]) for p in row[:6]] == [1, -1, -2, 2, 3, 4]
    # Then the other rows by their distance to the start's tilt.
    order = [t for t, _ in itertools.groupby(t for _, t in views)]
    assert [abs(t - 2.0) for t in order] == sorted(abs(t - 2.0) for t in order)
    # First towards lower pan when the target was last seen moving that way.
    left = search_views((10.0, 2.0), (-100.0, 100.0), (-25.0, 25.0), step, -1)
    assert left[0][0] < 10.0


def test_automatic_acquisition_that_sees_nothing_sweeps_with_dwells() -> None:
    h = Harness(SEARCH)
    h.run(0.2)
    h.sched.arm_search(h.now)
    armed_at = h.now
    h.run(6.0)
    moves = [(t, a) for t, a in _pan_tilt_commands(h) if isinstance(a, PanTiltAbsolute)]
    assert moves, "no sweep"
    first_t = moves[0][0]
    assert first_t >= armed_at + SEARCH.search_after_s
    assert first_t < armed_at + SEARCH.search_after_s + 0.2
    # One view per move completion and dwell (the model camera completes a move in 20 ms).
    gaps = [b - a for (a, _), (b, _) in itertools.pairwise(moves)]
    assert min(gaps) >= SEARCH.search_dwell_s
    assert max(gaps) < SEARCH.search_dwell_s + 0.1
    views = search_views(
        (0.0, 0.0), SEARCH.pan_range_deg or (0, 0), SEARCH.tilt_range_deg or (0, 0),
        view_step_deg(SEARCH),
    )  # fmt: skip
    assert [(a.pan_deg, a.tilt_deg) for _, a in moves] == views[: len(moves)]
    status = h.sched.search_status
    assert status is not None
    assert status.phase == "sweeping"
    assert status.pass_number == 1
    assert status.view == len(moves)
    assert status.views == len(views)
    assert not [a for _, a in _pan_tilt_commands(h) if isinstance(a, PanTiltDrive)]


def test_a_sighting_ends_the_sweep_and_the_head_follows() -> None:
    h = Harness(SEARCH)
    h.sched.arm_search(0.0)
    h.run(2.0)
    assert h.sched.search_status is not None
    assert h.sched.search_status.phase == "sweeping"
    h.centroid = (600.0, 239.5)  # the target shows at the right of the frame
    t0 = h.now
    h.run(1.0)
    after = [a for t, a in _pan_tilt_commands(h) if t > t0 + 0.1]
    assert not [a for a in after if isinstance(a, PanTiltAbsolute)], "still sweeping"
    assert any(isinstance(a, PanTiltDrive) and a.pan_rate_deg_s > 0 for a in after)
    assert h.sched.search_status is None  # following, nothing to say


def test_the_sweep_looks_at_the_acquisition_focus() -> None:
    h = Harness(replace(SEARCH, initial_focus_counts=None), plan=None)
    h.sched.set_track_focus(7000)  # the service's initial focus: the first one given
    h.run(0.5)
    h.sched.set_track_focus(9000)  # a later depth the scheduler was told to hold
    h.run(0.5)
    h.sched.arm_search(h.now)
    t0 = h.now
    h.run(2.0)
    moves = [a.counts for t, a in h.actions if isinstance(a, FocusMove) and t > t0]
    assert moves[-1] == 7000


def test_a_pass_that_finds_nothing_returns_holds_and_sweeps_again() -> None:
    h = Harness(SMALL)
    h.sched.arm_search(0.0)
    h.run(12.0)
    moves = [(t, a) for t, a in _pan_tilt_commands(h) if isinstance(a, PanTiltAbsolute)]
    views = search_views(
        (0.0, 0.0), SMALL.pan_range_deg or (0, 0), SMALL.tilt_range_deg or (0, 0),
        view_step_deg(SMALL),
    )  # fmt: skip
    n = len(views)
    assert n == 8  # 3 x 3 views less the start
    back = moves[n]
    assert (back[1].pan_deg, back[1].tilt_deg) == (0.0, 0.0)  # back where it began
    second = moves[n + 1]
    assert second[0] - back[0] >= SMALL.search_retry_s
    assert (second[1].pan_deg, second[1].tilt_deg) == views[0]
    status = h.sched.search_status
    assert status is not None
    assert status.pass_number == 2


def test_holding_after_a_pass_is_reported_with_the_next_pass() -> None:
    h = Harness(SMALL)
    h.sched.arm_search(0.0)
    h.run(5.0)
    status = h.sched.search_status
    assert status is not None
    assert status.phase == "holding"
    assert status.next_pass_at is not None
    assert status.next_pass_at > h.now
    assert status.start_deg == (0.0, 0.0)


def test_release_disarms_the_sweep() -> None:
    h = Harness(SEARCH, centroid=(600.0, 239.5))
    h.sched.arm_search(0.0)
    h.run(0.3)
    h.sched.stop_pan_tilt()
    h.centroid = None
    t0 = h.now
    h.run(4.0)
    assert [a for t, a in _pan_tilt_commands(h) if t >= t0] == [PanTiltStop()]
    assert h.sched.search_status is None
    assert not h.sched.search_armed


def test_an_roi_acquisition_sweeps_only_after_a_sighting_and_a_loss() -> None:
    h = Harness(SEARCH)
    h.sched.arm_search(0.0)
    h.sched.disarm_search()  # acquire in an ROI: the operator points at the view
    h.run(3.0)
    assert not [a for _, a in _pan_tilt_commands(h) if isinstance(a, PanTiltAbsolute)]
    h.centroid = (319.5, 239.5)
    h.run(0.5)
    assert h.sched.search_armed  # seen once: from now on a loss is searched for
    h.centroid = None
    t0 = h.now
    h.run(10.0)
    moves = [(t, a) for t, a in _pan_tilt_commands(h) if isinstance(a, PanTiltAbsolute)]
    # The loss first returns to where the target was last seen (one absolute move), then holds
    # search_after_s there before the sweep's views.
    assert len(moves) > 2
    back_t = moves[0][0]
    assert moves[1][0] - back_t >= SEARCH.search_after_s
    assert moves[1][0] > t0


def test_no_sweep_without_ranges_or_delay() -> None:
    for cfg in (replace(SEARCH, search_after_s=None), replace(SEARCH, pan_range_deg=None)):
        h = Harness(cfg)
        h.sched.arm_search(0.0)
        h.run(3.0)
        assert not _pan_tilt_commands(h)
        assert h.sched.search_status is None


def test_search_config_is_checked() -> None:
    with pytest.raises(ValueError, match="search_overlap"):
        Scheduler(replace(SEARCH, search_overlap=1.0))
    with pytest.raises(ValueError, match="pan_range_deg"):
        Scheduler(replace(SEARCH, pan_range_deg=(5.0, -5.0)))
