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

from dffd.core.filters import _SMALL, Differentiator, Mat2, expm2_floats

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


def image_shift(
    point_px: tuple[float, float],
    image_size: tuple[int, int],
    focal_length_px: float,
    head_from: tuple[float, float],
    head_to: tuple[float, float],
) -> tuple[float, float]:
    """The image motion of a world-fixed point seen at ``point_px`` when the head turns from
    ``head_from`` to ``head_to`` (pan, tilt in degrees): where the point is then, minus where it
    was. Exactly (0.0, 0.0) when the head did not move."""
    if head_from == head_to:
        return 0.0, 0.0
    w, h = image_size
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    u, v = point_px
    x, y, z = to_world(((u - cx) / focal_length_px, (v - cy) / focal_length_px, 1.0), *head_from)
    # the world direction in the camera frame at head_to: R_world_cam(head_to)ᵀ, written out
    p, t = math.radians(head_to[0]), math.radians(head_to[1])
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    xc = cp * x - sp * z
    yc = sp * st * x + ct * y + cp * st * z
    zc = sp * ct * x - st * y + cp * ct * z
    if zc <= 0.0:
        return 0.0, 0.0  # behind the camera: no turn between two frames does this
    return cx + focal_length_px * xc / zc - u, cy + focal_length_px * yc / zc - v


class VelocityEstimator:
    """Smoothed derivative of a 3-vector: one :class:`Differentiator` per axis.

    The three axes share the filter and the step, so the transition is evaluated once and each
    axis does the Differentiator's own float arithmetic (the same values; this runs twice on
    every frame with an estimate, where three Differentiator calls cost ~3× as much).
    """

    def __init__(self, omega: float) -> None:
        self._omega = omega
        proto = Differentiator(omega)  # the filter's matrices, as Differentiator builds them
        self._m: Mat2 = proto._m
        self._b = proto._b
        self._det = self._m[0] * self._m[3] - self._m[1] * self._m[2]
        self._axes: list[Differentiator] | None = None  # the singular case only (tiny ω)
        if not abs(self._det) > _SMALL:
            self._axes = [Differentiator(omega) for _ in range(3)]
        self._x: list[tuple[float, float]] | None = None

    def reset(self) -> None:
        """Forget the history (next update starts at rest)."""
        self._x = None
        if self._axes is not None:
            self._axes = [Differentiator(self._omega) for _ in range(3)]

    def update(self, p: Vec3, dt: float) -> Vec3:
        """Feed a position held over ``dt``; return the velocity estimate."""
        if self._axes is not None:
            v = [ax.update(c, dt)[1] for ax, c in zip(self._axes, p, strict=True)]
            return v[0], v[1], v[2]
        xs = self._x
        if xs is None:
            self._x = [(float(c), 0.0) for c in p]
            return 0.0, 0.0, 0.0
        if dt > 0:
            m00, m01, m10, m11 = self._m
            p00, p01, p10, p11 = expm2_floats((m00 * dt, m01 * dt, m10 * dt, m11 * dt))
            det, b = self._det, self._b
            out = []
            for (x0, x1), c in zip(xs, p, strict=True):
                # Differentiator.update: ZOH of u = (0, b c), ∫exp(Mτ)dτ u = M⁻¹ (Φ − I) u
                u1 = b * c
                r0 = (p00 - 1.0) * 0.0 + p01 * u1
                r1 = p10 * 0.0 + (p11 - 1.0) * u1
                g0 = (m11 * r0 - m01 * r1) / det
                g1 = (m00 * r1 - m10 * r0) / det
                out.append((p00 * x0 + p01 * x1 + g0, p10 * x0 + p11 * x1 + g1))
            self._x = xs = out
        return xs[0][1], xs[1][1], xs[2][1]
