"""Target position in the camera and world frames from the image centroid, ẑ and pan/tilt.

Conventions: camera frame x right, y down, z along the optical axis (OpenCV); the world frame is
the camera frame at pan = tilt = 0 with its origin at the rotation centre (the offset between the
rotation centre and the optical centre is neglected). Positive pan turns the camera to the right,
positive tilt turns it up: ``R_world_cam = R_pan(pan) @ R_tilt(tilt)``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.filters import Differentiator

FloatArray = npt.NDArray[np.float64]
Vec3 = tuple[float, float, float]


def camera_point(
    centroid_px: tuple[float, float],
    z_m: float,
    image_size: tuple[int, int],
    pixel_pitch_mm: float,
    image_distance_mm: float,
) -> Vec3:
    """Back-project the centroid at depth ``z_m``; principal point at the image centre."""
    w, h = image_size
    scale = pixel_pitch_mm / image_distance_mm * z_m
    return (
        (centroid_px[0] - (w - 1) / 2.0) * scale,
        (centroid_px[1] - (h - 1) / 2.0) * scale,
        z_m,
    )


def world_rotation(pan_deg: float, tilt_deg: float) -> FloatArray:
    """Rotation taking camera-frame vectors to the world frame."""
    p, t = math.radians(pan_deg), math.radians(tilt_deg)
    r_pan = np.array(
        [[math.cos(p), 0.0, math.sin(p)], [0.0, 1.0, 0.0], [-math.sin(p), 0.0, math.cos(p)]]
    )
    r_tilt = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]]
    )
    return np.asarray(r_pan @ r_tilt, dtype=np.float64)


def to_world(point_cam: Vec3, pan_deg: float, tilt_deg: float) -> Vec3:
    """Camera-frame point to the world frame."""
    # world_rotation() written out on floats (once per tracking frame; NumPy's per-call
    # overhead on a 3×3 is most of the cost): R_pan @ R_tilt =
    # [[cp, sp st, sp ct], [0, ct, −st], [−sp, cp st, cp ct]]
    p, t = math.radians(pan_deg), math.radians(tilt_deg)
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    x, y, z = point_cam
    return (
        cp * x + sp * st * y + sp * ct * z,
        ct * y - st * z,
        -sp * x + cp * st * y + cp * ct * z,
    )


class VelocityEstimator:
    """Smoothed derivative of a 3-vector (one :class:`Differentiator` per axis)."""

    def __init__(self, omega: float) -> None:
        self._omega = omega
        self._axes = [Differentiator(omega) for _ in range(3)]

    def reset(self) -> None:
        """Forget the history (next update starts at rest)."""
        self._axes = [Differentiator(self._omega) for _ in range(3)]

    def update(self, p: Vec3, dt: float) -> Vec3:
        """Feed a position held over ``dt``; return the velocity estimate."""
        v = [ax.update(c, dt)[1] for ax, c in zip(self._axes, p, strict=True)]
        return v[0], v[1], v[2]
