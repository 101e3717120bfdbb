"""Frame scheduler: interleaves three-focus bursts with tracking frames and centres the target.

Pure and synchronous: no I/O, no clock of its own (docs/design.md §5). One idea per module:

- :mod:`~dffd.scheduler.facade`: :class:`Scheduler`, the event-driven facade the shells drive;
- :mod:`~dffd.scheduler.config`: :class:`SchedulerConfig`;
- :mod:`~dffd.scheduler.actions`: the actions it returns (:class:`FocusMove`, …);
- :mod:`~dffd.scheduler.clock`: the exposure clock (predicted exposure windows);
- :mod:`~dffd.scheduler.focus`: the focus history (stationary intervals, for tagging);
- :mod:`~dffd.scheduler.bursts`: burst planning and the claims awaiting their frames;
- :mod:`~dffd.scheduler.head`: the pan/tilt head model and centring controller;
- :mod:`~dffd.scheduler.search`: the search sweep when automatic acquisition finds nothing;
- :mod:`~dffd.scheduler.geometry`: image angles and the pan/tilt speed table;
- :mod:`~dffd.scheduler.wire` and :mod:`~dffd.scheduler.budget`: VISCA message times and the
  link budget (focus move times, the theoretical depth rate);
- :mod:`~dffd.scheduler.stats`: the counters.
"""

from __future__ import annotations

from dffd.scheduler.actions import (
    PAN_TILT_ACTIONS,
    Action,
    FocusInquiry,
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
)
from dffd.scheduler.budget import RateLimit, depth_rate_limit, focus_move_time_s
from dffd.scheduler.bursts import order_settings
from dffd.scheduler.config import SchedulerConfig
from dffd.scheduler.facade import Phase, Scheduler
from dffd.scheduler.geometry import (
    nearest_speed_index,
    pixel_offset_to_deg,
    speed_of_index,
    visca_speed_index,
)
from dffd.scheduler.search import SearchStatus, search_views
from dffd.scheduler.stats import SchedulerStats
from dffd.scheduler.wire import link_time_s

__all__ = [
    "PAN_TILT_ACTIONS",
    "Action",
    "FocusInquiry",
    "FocusMove",
    "PanTiltAbsolute",
    "PanTiltDrive",
    "PanTiltInquiry",
    "PanTiltStop",
    "Phase",
    "RateLimit",
    "Scheduler",
    "SchedulerConfig",
    "SchedulerStats",
    "SearchStatus",
    "depth_rate_limit",
    "focus_move_time_s",
    "link_time_s",
    "nearest_speed_index",
    "order_settings",
    "pixel_offset_to_deg",
    "search_views",
    "speed_of_index",
    "visca_speed_index",
]
