"""The 3D tracker's measurements from the core's outputs: direction and size, and burst sizes.

The fused depth the pipeline publishes is a filtered quantity: its errors are correlated from
frame to frame (lag-1 autocorrelation ≈ 0.6 on the reference simulator), which a tracker fed
with it every frame takes as white. The tracker is fed instead the two raw channels the depth
filters themselves fuse, each with errors close to white (docs/tracking3d.md):

* every tracking frame: the target's direction (centroid, pan/tilt) and its normalised image
  size ``s = r·pitch/F = R/z`` — the *unit-size point* ``m`` with ``p = R m``, where the size
  ``R`` is a state of the tracker;
* every accepted burst: the size ``R_k = z_m · s(t_b)`` — the burst's depth times the image
  size at the burst's effective time (log-interpolated between the tracking frames around it,
  as the pipeline transports its measurements), with σ ``s(t_b) σ_z``.

Pure: the caller hands in times, pixels, angles and depths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core.tracking3d import CameraModel, DirectionSize, Tracker3DConfig, unit_size_point

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class FeedFrame:
    """One tracking frame: time, centroid, pan/tilt and normalised size ``s`` (= R/z)."""

    t: float
    centroid_px: tuple[float, float]
    pan_deg: float
    tilt_deg: float
    size_ratio: float


class SizeFeed:
    """Turns tracking frames and burst depths into :meth:`Tracker3D.step_size` arguments."""

    def __init__(self, config: Tracker3DConfig) -> None:
        self.config = config
        self._pending: tuple[float, float, float] | None = None  # (t, z_m, σ_z) of a burst
        self._prev: tuple[float, float] | None = None  # (t, s) of the last tracking frame

    def reset(self) -> None:
        """Forget the pending burst and the last frame (a new target)."""
        self._pending = None
        self._prev = None

    def burst(self, t: float, z_m: float, sigma_z_m: float) -> None:
        """An accepted burst: the depth ``z_m`` (σ) at its effective time ``t`` (the burst's
        mid-time plus the pipeline's ``measurement_time_offset_s``); used at the next tracking
        frame."""
        self._pending = (t, z_m, sigma_z_m)

    def frame(
        self, frame: FeedFrame, camera: CameraModel
    ) -> tuple[tuple[FloatArray, FloatArray], tuple[float, float] | None]:
        """The frame's unit-size point ``(m, Σ_m)`` and the pending burst's ``(R, σ_R²)``."""
        cfg = self.config
        meas = DirectionSize(
            frame.centroid_px,
            frame.pan_deg,
            frame.tilt_deg,
            frame.size_ratio,
            cfg.sigma_size_rel,
            cfg.sigma_px,
            cfg.sigma_angle_deg,
        )
        unit = unit_size_point(meas, camera)
        size: tuple[float, float] | None = None
        if self._pending is not None:
            t_b, z_m, sigma_z = self._pending
            self._pending = None
            s_b = self._size_at(t_b, frame.t, frame.size_ratio)
            sigma_r = cfg.burst_sigma_scale * sigma_z * s_b
            size = (z_m * s_b, sigma_r * sigma_r)
        self._prev = (frame.t, frame.size_ratio)
        return unit, size

    def _size_at(self, t_b: float, t_now: float, s_now: float) -> float:
        """``s`` at ``t_b``, log-interpolated between the last and this tracking frame (at most
        one step extrapolated), as :class:`dffd.core.pipeline.Pipeline` transports a burst."""
        if self._prev is None or not self._prev[0] < t_now:
            return s_now
        t0, s0 = self._prev
        w = min(max((t_b - t0) / (t_now - t0), -1.0), 1.0)
        return math.exp((1.0 - w) * math.log(s0) + w * math.log(s_now))
