"""The 3D tracker's measurements from the core's outputs: direction and size, and burst sizes.

The fused depth the pipeline publishes is a filtered quantity: its errors are correlated from
frame to frame (lag-1 autocorrelation ≈ 0.6 on the reference simulator), which a tracker fed
with it every frame takes as white. The tracker is fed instead the two raw channels the depth
filters themselves fuse, each with errors close to white (docs/tracking3d.md):

* every tracking frame: the target's direction (centroid, pan/tilt) and its normalised image
  size ``s = r·pitch/F = R/z`` — the *unit-size point* ``m`` with ``p = R m``, where the size
  ``R`` is a state of the tracker;
* every accepted burst: the pipeline's own size measurement ``R_k = z_m · s(t_b + τ̂)`` — the
  burst's depth times the image size at its effective time, read from the pipeline's per-frame
  size history and corrected for the burst's lean ``τ̂`` (:attr:`Pipeline.size_measurement`),
  with σ ``c · s σ_z``. ``R`` is a constant, so the measurement needs no transport: it is
  folded in at the next tracking frame.

Pure: the caller hands in times, pixels, angles and sizes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core.tracking3d_camera import CameraModel, unit_size_point_of
from dffd.core.tracking3d_types import Tracker3DConfig

FloatArray = npt.NDArray[np.float64]


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__, and one is built on every tracking frame.
@dataclass(slots=True)
class FeedFrame:
    """One tracking frame: time, centroid, pan/tilt and normalised size ``s`` (= R/z)."""

    t: float
    centroid_px: tuple[float, float]
    pan_deg: float
    tilt_deg: float
    size_ratio: float


class SizeFeed:
    """Turns tracking frames and burst sizes into :meth:`Tracker3D.step_size` arguments."""

    def __init__(self, config: Tracker3DConfig) -> None:
        self.config = config
        self._pending: tuple[float, float] | None = None  # (R, σ_R) of the last burst

    def reset(self) -> None:
        """Forget the pending burst (a new target)."""
        self._pending = None

    def burst(self, size_m: float, sigma_m: float) -> None:
        """An accepted burst's size ``R`` (m) and its σ, as the pipeline measured it
        (:attr:`dffd.core.pipeline.Pipeline.size_measurement`); used at the next tracking frame
        (a later burst before it replaces it)."""
        self._pending = (size_m, sigma_m)

    def frame(
        self, frame: FeedFrame, camera: CameraModel
    ) -> tuple[tuple[FloatArray, FloatArray], tuple[float, float] | None]:
        """The frame's unit-size point ``(m, Σ_m)`` and the pending burst's ``(R, σ_R²)``, its σ
        scaled by ``burst_sigma_scale``."""
        cfg = self.config
        # unit_size_point of the frame's DirectionSize, without building one (every frame)
        unit = unit_size_point_of(
            frame.centroid_px,
            frame.pan_deg,
            frame.tilt_deg,
            frame.size_ratio,
            cfg.sigma_size_rel,
            cfg.sigma_px,
            cfg.sigma_angle_deg,
            camera,
        )
        size: tuple[float, float] | None = None
        if self._pending is not None:
            size_m, sigma_m = self._pending
            self._pending = None
            sigma_r = cfg.burst_sigma_scale * sigma_m
            size = (size_m, sigma_r * sigma_r)
        return unit, size
