"""VISCA message sizes and their time on the serial line (docs/design.md §6).

The link budget (:mod:`dffd.scheduler.budget`) and the pan/tilt head model count time in these.
"""

from __future__ import annotations

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
FOCUS_DIRECT_BYTES = 9  # 8x 01 04 48 0p 0q 0r 0s FF
ACK_BYTES = 3  # z0 4y FF
COMPLETION_BYTES = 3  # z0 5y FF
PAN_TILT_DRIVE_BYTES = 9  # 8x 01 06 01 VV WW XX YY FF
PAN_TILT_ABSOLUTE_BYTES = 15  # 8x 01 06 02 VV WW 0Y×4 0Z×4 FF
PAN_TILT_POSITION_REPLY_BYTES = 11  # z0 50 0w×4 0z×4 FF


def link_time_s(n_bytes: int, baudrate: int) -> float:
    """Time to clock ``n_bytes`` through an 8N1 serial line."""
    return n_bytes * BITS_PER_BYTE / baudrate
