"""The camera between the world and the 3D trackers: a frame's measurement as a world point.

**Measurement.** The target's direction (image centroid through the camera model — principal
point, pixel pitch, image distance — and the pan/tilt angles) and the fused depth ``z`` along
the optical axis, each with its σ. It is *converted* to a Cartesian world point with the
covariance propagated through the Jacobian of the conversion (:func:`cartesian_measurement`),
rather than updated by an EKF on (direction, depth). Why: the angular errors are tiny (a tenth
of a pixel is ~2·10⁻⁵ rad at f = 31 mm, p = 5 µm; the pan/tilt readback ~3.5·10⁻⁴ rad), so the
conversion's linearisation error — of order ``z σ_θ²`` — is microns, far below the depth σ; the
converted measurement is then exactly linear in the state (``H = [I 0 …]``), identical for every
model, so the models' innovation likelihoods are computed on the same quantity and IMM mixing
stays linear. The covariance is strongly elongated along the line of sight (depth σ of
centimetres, lateral σ of millimetres) and that shape is what the filters use
(:mod:`dffd.core.tracking3d`). A direction and apparent size converts the same way at the depth
``1/s`` (:func:`unit_size_point`).

The way back: the pan/tilt rate that follows an estimated motion (:func:`direction_rate_deg_s`).
Pure; frames in ``docs/tracking3d.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core import kernel_dispatch
from dffd.core.tracking3d_types import Track3DEstimate

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Pinhole back-projection: principal point (px), pixel pitch and image distance (mm)."""

    principal_point_px: tuple[float, float]
    pixel_pitch_mm: float
    image_distance_mm: float  # lens-to-sensor distance (≈ f at long range), as geometry.py uses

    @classmethod
    def centred(
        cls, image_size: tuple[int, int], pixel_pitch_mm: float, image_distance_mm: float
    ) -> CameraModel:
        """Principal point at the image centre, as :func:`dffd.core.geometry.camera_point`."""
        w, h = image_size
        return cls(((w - 1) / 2.0, (h - 1) / 2.0), pixel_pitch_mm, image_distance_mm)


@dataclass(frozen=True, slots=True)
class DirectionDepth:
    """One frame's measurement: centroid, pan/tilt and depth along the optical axis, with σ."""

    centroid_px: tuple[float, float]
    pan_deg: float
    tilt_deg: float
    z_m: float
    sigma_z_m: float
    sigma_px: float = 0.3  # centroid σ per axis
    sigma_angle_deg: float = 0.02  # pan/tilt readback σ per axis (EVI-D100: 1/14.4°/√12)


@dataclass(frozen=True, slots=True)
class DirectionSize:
    """One frame's direction and apparent size: centroid, pan/tilt and ``s = r·pitch/F``.

    ``s`` is the normalised image size (``= R/z`` for a target of size ``R`` at depth ``z``);
    ``sigma_size_rel`` is its relative σ (σ_s/s).
    """

    centroid_px: tuple[float, float]
    pan_deg: float
    tilt_deg: float
    size_ratio: float
    sigma_size_rel: float
    sigma_px: float = 0.3  # centroid σ per axis
    sigma_angle_deg: float = 0.02  # pan/tilt σ per axis


def cartesian_measurement(
    meas: DirectionDepth, camera: CameraModel
) -> tuple[FloatArray, FloatArray]:
    """World point of the measurement and its covariance (first-order propagation)."""
    return _cartesian(
        meas.centroid_px,
        meas.pan_deg,
        meas.tilt_deg,
        meas.z_m,
        meas.sigma_z_m,
        meas.sigma_px,
        meas.sigma_angle_deg,
        camera,
    )


def unit_size_point(meas: DirectionSize, camera: CameraModel) -> tuple[FloatArray, FloatArray]:
    """World point ``m`` of a target of unit size (``p = R m``) and its covariance.

    ``m = R(pan, tilt) · (k(u − cx), k(v − cy), 1) / s`` is the Cartesian conversion at the depth
    ``1/s`` with the relative size σ as its relative depth σ, so the covariance is
    :func:`cartesian_measurement`'s.
    """
    return unit_size_point_of(
        meas.centroid_px,
        meas.pan_deg,
        meas.tilt_deg,
        meas.size_ratio,
        meas.sigma_size_rel,
        meas.sigma_px,
        meas.sigma_angle_deg,
        camera,
    )


def unit_size_point_of(  # noqa: PLR0917 - the fields of a DirectionSize, without building one
    centroid_px: tuple[float, float],
    pan_deg: float,
    tilt_deg: float,
    size_ratio: float,
    sigma_size_rel: float,
    sigma_px: float,
    sigma_angle_deg: float,
    camera: CameraModel,
) -> tuple[FloatArray, FloatArray]:
    """:func:`unit_size_point` of a :class:`DirectionSize` with these fields (a frame's call)."""
    z = 1.0 / size_ratio
    return _cartesian(
        centroid_px, pan_deg, tilt_deg, z, sigma_size_rel * z, sigma_px, sigma_angle_deg, camera
    )


def direction_rate_deg_s(est: Track3DEstimate) -> tuple[float, float]:
    """Pan/tilt rate (deg/s) of the direction to the estimated target, the head's frame.

    The direction that centres ``p`` is ``pan = atan2(x, z)``, ``tilt = atan2(−y, h)`` with
    ``h = √(x² + z²)`` (docs/tracking3d.md: positive pan right, positive tilt up, y down); their
    time derivatives along the estimated velocity.
    """
    x, y, z = est.position_m
    vx, vy, vz = est.velocity_m_s
    h2 = x * x + z * z
    if not h2 > 0.0:
        return 0.0, 0.0
    h = math.sqrt(h2)
    pan_rate = (z * vx - x * vz) / h2
    h_dot = (x * vx + z * vz) / h
    tilt_rate = (-vy * h + y * h_dot) / (h2 + y * y)
    return math.degrees(pan_rate), math.degrees(tilt_rate)


def _cartesian(  # noqa: PLR0917 - a DirectionDepth's fields
    centroid_px: tuple[float, float],
    pan_deg: float,
    tilt_deg: float,
    z: float,
    sigma_z_m: float,
    sigma_px: float,
    sigma_angle_deg: float,
    camera: CameraModel,
) -> tuple[FloatArray, FloatArray]:
    """:func:`cartesian_measurement` on the measurement's fields."""
    # one kernel call (the float operations as the NumPy twin writes them out: once per
    # tracking frame, where Python's floats and the two array builds cost ~20 µs)
    world, cov = np.empty(3), np.empty((3, 3))
    kernel_dispatch.current().cartesian_point(
        centroid_px[0], centroid_px[1], pan_deg, tilt_deg, z, sigma_z_m, sigma_px,
        sigma_angle_deg, camera.pixel_pitch_mm, camera.image_distance_mm,
        camera.principal_point_px[0], camera.principal_point_px[1], world, cov,
    )  # fmt: skip
    return world, cov
