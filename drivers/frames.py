"""Frames and the frame-source protocol shared by the real capture path and the simulator."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt


class FrameSourceError(Exception):
    """Root of frame-source errors."""


class FrameTimeoutError(FrameSourceError, TimeoutError):
    """No frame arrived within the allowed time."""


@dataclass(frozen=True, slots=True)
class Frame:
    """One exposed image from any frame source."""

    index: int
    t: float  # exposure mid-time, monotonic seconds (the source's clock)
    image: npt.NDArray[np.uint8]  # H×W uint8 gray or H×W×3 BGR


@runtime_checkable
class FrameSource(Protocol):
    """An async stream of frames; implemented by OpenCV capture and by the simulated camera."""

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        ...

    @property
    def fps(self) -> float:
        """Nominal frame rate."""
        ...

    @property
    def dropped_frames(self) -> int:
        """Frames lost by the source (not delivered to the caller) since it started."""
        ...

    async def start(self) -> None:
        """Open the device and begin delivering frames."""
        ...

    async def next_frame(self) -> Frame:
        """Return the next frame (callers bound the wait with ``asyncio.timeout``)."""
        ...

    async def close(self) -> None:
        """Stop delivering frames and release the device; idempotent."""
        ...
