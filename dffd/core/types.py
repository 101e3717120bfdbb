"""Core data types shared by the scheduler, the estimation core, recordings and the bench."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

FrameRole = Literal["track", "burst", "transit"]


@dataclass(frozen=True, slots=True)
class FrameTag:
    """What the scheduler knew about one exposure (docs/design.md §5)."""

    role: FrameRole
    focus_counts: int | None  # None for transit frames (the lens moved during the exposure)
    pan_deg: float
    tilt_deg: float
    burst: tuple[int, int] | None = None  # (burst id, slot) for burst frames
