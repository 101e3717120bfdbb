"""The simulated world: one planar target moving in 3D in front of the pan/tilt head.

Frame: the camera frame at pan = tilt = 0 (OpenCV: x right, y down, z forward, metres), the
pan/tilt head at the origin; "horizontal" is the x–z plane. The target is a flat card that always
faces the camera (its plane is perpendicular to the line of sight, as the paper assumes of the
target boundary) and may spin about the line of sight. Its size ``R`` is ``sqrt(tr Σ)`` of its
boundary sampled uniformly in arc length (docs/design.md §3) — for a disc, the radius.

Target-plane coordinates ``(a, b)``: ``a`` horizontal to the right, ``b`` downwards, as seen from
the camera; textures are stored with rows along ``+b``.

Times given to trajectories are scenario seconds (0 at the start of the run).

3D truth: every trajectory gives its position, velocity and acceleration analytically
(:meth:`Trajectory.kinematics`); the *angular speed* is the turn rate of the velocity about the
upward vertical ``u = −y``, ``ω = ((v × a) · u) / |v_h|²`` (positive counter-clockwise seen from
above, i.e. turning +x towards +z; 0 when the horizontal speed is below
:data:`TURN_RATE_MIN_SPEED_M_S`). On a horizontal circle it is ``±v/R``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.config import TargetConfig, TrajectoryConfig, WorldConfig
from drivers.sim.outline import irregular_unit_outline

FloatArray = npt.NDArray[np.float64]

DISC_VERTICES = 256  # outline polygon of a disc: sagitta error 0.0075 px at r = 100 px
BOUNDARY_SAMPLES = 1024  # uniform arc-length samples for sqrt(tr Σ) and truth centroids
TEXTURE_PX = 256  # texture resolution across the card
RANDOM_COMPONENTS = 4  # sinusoids per axis of the smooth random path
RANDOM_SPEED_WINDOW = 500.0  # unit-time span over which the random path's mean speed is measured
ARC_TABLE_SAMPLES = 4096  # parameter samples for constant-speed parametrisation of closed curves
ARUCO_QUIET_MODULES = 1  # white border around the marker, in cells (the card is the boundary)
# Below this horizontal speed (m/s) the direction of motion — hence the turn rate — is undefined
# and reported as 0 (a target at rest or moving vertically does not turn).
TURN_RATE_MIN_SPEED_M_S = 1e-6


@dataclass(frozen=True, slots=True)
class Kinematics:
    """Position, velocity and acceleration (world frame) and the turn rate at one time."""

    position_m: FloatArray
    velocity_mps: FloatArray
    acceleration_mps2: FloatArray

    @property
    def angular_speed_rad_s(self) -> float:
        """Turn rate of the velocity about the upward vertical (see the module docstring)."""
        return turn_rate(self.velocity_mps, self.acceleration_mps2)


def turn_rate(velocity: FloatArray, acceleration: FloatArray) -> float:
    """``((v × a) · u) / |v_h|²`` with ``u = −y`` (up); 0 for a horizontal speed near zero."""
    vx, vz = float(velocity[0]), float(velocity[2])
    ax, az = float(acceleration[0]), float(acceleration[2])
    speed2 = vx * vx + vz * vz
    if speed2 < TURN_RATE_MIN_SPEED_M_S**2:
        return 0.0
    return (vx * az - vz * ax) / speed2


class Trajectory(Protocol):
    """Target position as a function of scenario time."""

    def position(self, t: float) -> FloatArray:
        """Position (m) in the world frame at time ``t`` (s)."""
        ...

    def kinematics(self, t: float) -> Kinematics:
        """Position, velocity and acceleration at time ``t``, analytically."""
        ...


@dataclass(frozen=True, slots=True)
class StaticPath:
    """At rest."""

    point: FloatArray

    def position(self, t: float) -> FloatArray:
        """Always the same point."""
        return self.point.copy()

    def kinematics(self, t: float) -> Kinematics:
        """At rest."""
        return Kinematics(self.point.copy(), np.zeros(3), np.zeros(3))


@dataclass(frozen=True, slots=True)
class LinearPath:
    """From ``start`` towards ``end`` at constant speed, then at rest at ``end``."""

    start: FloatArray
    end: FloatArray
    speed_mps: float

    def position(self, t: float) -> FloatArray:
        """Straight-line motion, clamped at the end point."""
        span = self.end - self.start
        length = float(np.linalg.norm(span))
        if length == 0.0 or self.speed_mps == 0.0:
            return self.start.copy()
        travelled = min(max(t, 0.0) * self.speed_mps, length)
        return self.start + span * (travelled / length)

    def kinematics(self, t: float) -> Kinematics:
        """Constant velocity while moving (the start and the stop are velocity steps)."""
        span = self.end - self.start
        length = float(np.linalg.norm(span))
        moving = length > 0.0 and self.speed_mps > 0.0 and 0.0 <= t < length / self.speed_mps
        velocity = span * (self.speed_mps / length) if moving else np.zeros(3)
        return Kinematics(self.position(t), velocity, np.zeros(3))


@dataclass(frozen=True, slots=True)
class StopAndGoPath:
    """Shuttles between ``start`` and ``end``: each leg, then a rest of ``stop_s``.

    Along a leg of length ``L`` the speed is ``2 v̄ sin²(π τ / T)`` with ``T = L / v̄`` (``v̄`` =
    ``speed_mps``, the mean speed over the leg): it starts and stops smoothly (continuous
    acceleration, peak ``2π v̄² / L``), so the 3D truth has no impulses.
    """

    start: FloatArray
    end: FloatArray
    speed_mps: float
    stop_s: float

    def position(self, t: float) -> FloatArray:
        """Point at time ``t``."""
        return self.kinematics(t).position_m

    def kinematics(self, t: float) -> Kinematics:
        """Analytic position, velocity and acceleration."""
        span = self.end - self.start
        length = float(np.linalg.norm(span))
        if length == 0.0 or self.speed_mps == 0.0 or t <= 0.0:
            return Kinematics(self.start.copy(), np.zeros(3), np.zeros(3))
        unit = span / length
        leg_s = length / self.speed_mps
        period = leg_s + self.stop_s
        k = math.floor(t / period)
        tau = t - k * period
        forward = k % 2 == 0
        origin = self.start if forward else self.end
        direction = unit if forward else -unit
        if tau >= leg_s:
            return Kinematics(origin + direction * length, np.zeros(3), np.zeros(3))
        w = 2.0 * math.pi / leg_s
        s = length * (tau / leg_s - math.sin(w * tau) / (2.0 * math.pi))
        ds = self.speed_mps * (1.0 - math.cos(w * tau))
        dds = self.speed_mps * w * math.sin(w * tau)
        return Kinematics(origin + direction * s, direction * ds, direction * dds)


@dataclass(frozen=True, slots=True)
class CirclePath:
    """Horizontal circle; phase 0 is the point nearest the camera, moving towards +x."""

    center: FloatArray
    radius_m: float
    speed_mps: float
    phase_rad: float

    def position(self, t: float) -> FloatArray:
        """``(cx + R sin φ, cy, cz − R cos φ)`` with ``φ = phase + v t / R``."""
        phi = self.phase_rad + self.speed_mps * t / self.radius_m
        return self.center + self.radius_m * np.array([math.sin(phi), 0.0, -math.cos(phi)])

    def kinematics(self, t: float) -> Kinematics:
        """Uniform circular motion: turn rate ``+v/R`` (counter-clockwise from above)."""
        omega = self.speed_mps / self.radius_m
        phi = self.phase_rad + omega * t
        c, s = math.cos(phi), math.sin(phi)
        return Kinematics(
            self.center + self.radius_m * np.array([s, 0.0, -c]),
            self.speed_mps * np.array([c, 0.0, s]),
            self.speed_mps * omega * np.array([-s, 0.0, c]),
        )


class FigureEightPath:
    """Horizontal figure-eight ``(a sin 2φ, 0, a sin φ)`` around the centre at constant speed.

    Depth swings ±a once per lap while the target crosses the view sideways twice.
    """

    def __init__(
        self, center: FloatArray, half_extent_m: float, speed_mps: float, phase_rad: float
    ) -> None:
        self.center = center
        self.half_extent_m = half_extent_m
        self.speed_mps = speed_mps
        phi = np.linspace(0.0, 2.0 * math.pi, ARC_TABLE_SAMPLES + 1)
        pts = self._shape(phi)
        steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self._arc = np.concatenate(([0.0], np.cumsum(steps)))
        self._phi = phi
        self._s0 = float(np.interp(phase_rad % (2.0 * math.pi), phi, self._arc))

    @property
    def lap_length_m(self) -> float:
        """Path length of one lap."""
        return float(self._arc[-1])

    def position(self, t: float) -> FloatArray:
        """Point reached after ``t`` seconds at the path speed."""
        s = (self._s0 + self.speed_mps * t) % self.lap_length_m
        phi = float(np.interp(s, self._arc, self._phi))
        return np.asarray(self.center + self._shape(np.array([phi]))[0], dtype=np.float64)

    def kinematics(self, t: float) -> Kinematics:
        """Velocity ``v T`` and acceleration ``v² κ N`` from the curve's derivatives at φ(s)."""
        s = (self._s0 + self.speed_mps * t) % self.lap_length_m
        phi = float(np.interp(s, self._arc, self._phi))
        a = self.half_extent_m
        d1 = np.array([2.0 * a * math.cos(2.0 * phi), 0.0, a * math.cos(phi)])  # dP/dφ
        d2 = np.array([-4.0 * a * math.sin(2.0 * phi), 0.0, -a * math.sin(phi)])  # d²P/dφ²
        n1 = float(np.linalg.norm(d1))
        tangent = d1 / n1
        # With constant path speed v: dφ/dt = v/|P'|, a = v² (P'' − (P''·T) T) / |P'|².
        normal_part = d2 - float(d2 @ tangent) * tangent
        position = self.center + np.array([a * math.sin(2.0 * phi), 0.0, a * math.sin(phi)])
        v = self.speed_mps
        return Kinematics(position, v * tangent, v * v * normal_part / (n1 * n1))

    def _shape(self, phi: FloatArray) -> FloatArray:
        a = self.half_extent_m
        return np.stack((a * np.sin(2.0 * phi), np.zeros_like(phi), a * np.sin(phi)), axis=1)


class RandomPath:
    """Smooth seeded random path: per axis a sum of sinusoids that stays inside the half-box.

    Amplitudes sum to the half-extent of each axis; time is scaled so that the mean path speed
    over a long window equals ``speed_mps``.
    """

    def __init__(self, center: FloatArray, extent: FloatArray, speed_mps: float, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.center = center
        weights = rng.uniform(0.3, 1.0, size=(3, RANDOM_COMPONENTS))
        self._amp = extent[:, None] * weights / weights.sum(axis=1, keepdims=True)
        self._freq = rng.uniform(0.5, 1.5, size=(3, RANDOM_COMPONENTS))  # cycles per unit time
        self._phase = rng.uniform(0.0, 2.0 * math.pi, size=(3, RANDOM_COMPONENTS))
        tau = np.linspace(0.0, RANDOM_SPEED_WINDOW, 50_001)  # 0.01 unit steps
        vel = self._velocity_unit(tau)
        mean_speed = float(np.mean(np.linalg.norm(vel, axis=0)))
        self._time_scale = speed_mps / mean_speed if mean_speed > 0.0 else 0.0

    def position(self, t: float) -> FloatArray:
        """Point at time ``t``."""
        tau = t * self._time_scale
        offsets = np.sum(self._amp * np.sin(2.0 * math.pi * self._freq * tau + self._phase), axis=1)
        return np.asarray(self.center + offsets, dtype=np.float64)

    def kinematics(self, t: float) -> Kinematics:
        """Derivatives of the sums of sinusoids."""
        tau = t * self._time_scale
        w = 2.0 * math.pi * self._freq
        arg = w * tau + self._phase
        k = self._time_scale
        offsets = np.sum(self._amp * np.sin(arg), axis=1)
        velocity = k * np.sum(self._amp * w * np.cos(arg), axis=1)
        acceleration = -k * k * np.sum(self._amp * w * w * np.sin(arg), axis=1)
        return Kinematics(
            np.asarray(self.center + offsets, dtype=np.float64),
            np.asarray(velocity, dtype=np.float64),
            np.asarray(acceleration, dtype=np.float64),
        )

    def _velocity_unit(self, tau: FloatArray) -> FloatArray:
        arg = 2.0 * math.pi * self._freq[:, :, None] * tau[None, None, :] + self._phase[:, :, None]
        coeff = (self._amp * 2.0 * math.pi * self._freq)[:, :, None]
        return np.asarray(np.sum(coeff * np.cos(arg), axis=1), dtype=np.float64)


def make_trajectory(config: TrajectoryConfig) -> Trajectory:
    """The trajectory a config describes."""
    if config.kind == "static":
        return StaticPath(_vec(config.position_m))
    if config.kind == "linear":
        return LinearPath(_vec(config.position_m), _vec(config.end_m), config.speed_mps)
    if config.kind == "circle":
        return CirclePath(
            _vec(config.center_m), config.radius_m, config.speed_mps, math.radians(config.phase_deg)
        )
    if config.kind == "stop-and-go":
        return StopAndGoPath(
            _vec(config.position_m), _vec(config.end_m), config.speed_mps, config.stop_s
        )
    if config.kind == "figure-eight":
        return FigureEightPath(
            _vec(config.center_m), config.radius_m, config.speed_mps, math.radians(config.phase_deg)
        )
    return RandomPath(_vec(config.center_m), _vec(config.extent_m), config.speed_mps, config.seed)


@dataclass(frozen=True, slots=True)
class TargetShape:
    """A flat target: convex outline (target-plane metres) and an optional face texture."""

    kind: str
    size_m: float  # sqrt(tr Σ) of the boundary
    outline_m: FloatArray  # N×2 polygon vertices (a, b)
    boundary_m: FloatArray  # uniform arc-length samples of the outline
    foreground_dn: float
    texture: npt.NDArray[np.float32] | None = None  # DN, covering texture_half_m square
    texture_half_m: float = 0.0
    aruco_marker_side_m: float | None = None  # side of the black marker square (ArUco only)


def make_shape(config: TargetConfig) -> TargetShape:
    """The target a config describes, scaled so that its boundary's sqrt(tr Σ) is ``size_m``."""
    if config.shape == "disc":
        angles = np.linspace(0.0, 2.0 * math.pi, DISC_VERTICES, endpoint=False)
        unit = np.stack((np.cos(angles), np.sin(angles)), axis=1)
    elif config.shape == "irregular":
        unit = irregular_unit_outline(config.texture_seed)
    elif config.shape == "polygon":
        angles = np.linspace(0.0, 2.0 * math.pi, config.sides, endpoint=False) - math.pi / 2
        unit = np.stack((np.cos(angles), np.sin(angles)), axis=1)
    else:  # a square card
        unit = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    scale = config.size_m / rms_radius(boundary_samples(unit))
    outline = unit * scale
    boundary = boundary_samples(outline)
    if config.shape == "textured":
        half = scale
        return TargetShape(
            "textured",
            config.size_m,
            outline,
            boundary,
            config.foreground_dn,
            _blob_texture(config),
            half,
        )
    if config.shape == "aruco":
        texture, marker_fraction = _aruco_texture(config)
        return TargetShape(
            "aruco",
            config.size_m,
            outline,
            boundary,
            config.foreground_dn,
            texture,
            scale,
            aruco_marker_side_m=2.0 * scale * marker_fraction,
        )
    return TargetShape(config.shape, config.size_m, outline, boundary, config.foreground_dn)


def boundary_samples(polygon: FloatArray, n: int = BOUNDARY_SAMPLES) -> FloatArray:
    """``n`` points spaced uniformly in arc length along a closed polygon."""
    p = np.asarray(polygon, dtype=np.float64)
    closed = np.vstack((p, p[:1]))
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    arc = np.concatenate(([0.0], np.cumsum(seg)))
    s = np.arange(n) * (arc[-1] / n)
    return np.stack((np.interp(s, arc, closed[:, 0]), np.interp(s, arc, closed[:, 1])), axis=1)


def rms_radius(points: FloatArray) -> float:
    """sqrt(tr Σ) of a point set (the paper's rotation-invariant size)."""
    p = np.asarray(points, dtype=np.float64)
    return float(math.sqrt(np.sum(np.var(p, axis=0))))


@dataclass(frozen=True, slots=True)
class TargetPose:
    """Where the target is at one scenario time."""

    t: float
    position_m: FloatArray  # centre, world frame
    velocity_mps: FloatArray
    roll_rad: float  # rotation about the line of sight (clockwise as seen by the camera)
    acceleration_mps2: FloatArray = field(default_factory=lambda: np.zeros(3))
    angular_speed_rad_s: float = 0.0  # turn rate about the upward vertical (module docstring)


class World:
    """A target on a trajectory in front of the camera, over a uniform background."""

    def __init__(
        self,
        shape: TargetShape,
        trajectory: Trajectory,
        background_dn: float = 40.0,
        roll_deg: float = 0.0,
        rotation_dps: float = 0.0,
    ) -> None:
        self.shape = shape
        self.trajectory = trajectory
        self.background_dn = background_dn
        self._roll0 = math.radians(roll_deg)
        self._roll_rate = math.radians(rotation_dps)

    @classmethod
    def from_config(cls, config: WorldConfig) -> World:
        """Build from a validated config."""
        return cls(
            make_shape(config.target),
            make_trajectory(config.trajectory),
            config.background_dn,
            config.target.roll_deg,
            config.target.rotation_dps,
        )

    def pose(self, t: float) -> TargetPose:
        """The target's pose at scenario time ``t``."""
        kin = self.trajectory.kinematics(t)
        return TargetPose(
            t,
            kin.position_m,
            kin.velocity_mps,
            self._roll0 + self._roll_rate * t,
            kin.acceleration_mps2,
            kin.angular_speed_rad_s,
        )

    def to_world(self, pose: TargetPose, plane_points: FloatArray) -> FloatArray:
        """Target-plane points (N×2, m) to world points (N×3) for the card facing the camera."""
        e1, e2 = _plane_axes(pose.position_m)
        c, s = math.cos(pose.roll_rad), math.sin(pose.roll_rad)
        a = plane_points[:, 0] * c - plane_points[:, 1] * s
        b = plane_points[:, 0] * s + plane_points[:, 1] * c
        return pose.position_m[None, :] + a[:, None] * e1[None, :] + b[:, None] * e2[None, :]

    def outline_world(self, pose: TargetPose) -> FloatArray:
        """Outline vertices in the world frame."""
        return self.to_world(pose, self.shape.outline_m)

    def boundary_world(self, pose: TargetPose) -> FloatArray:
        """Uniform boundary samples in the world frame."""
        return self.to_world(pose, self.shape.boundary_m)

    def texture_corners_world(self, pose: TargetPose) -> FloatArray | None:
        """World positions of the texture's corners (TL, TR, BR, BL), if the target has one."""
        if self.shape.texture is None:
            return None
        h = self.shape.texture_half_m
        corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        return self.to_world(pose, corners)


# -- private helpers ------------------------------------------------------------------------


def _vec(values: tuple[float, float, float]) -> FloatArray:
    return np.asarray(values, dtype=np.float64)


def _plane_axes(position: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit vectors of the card's a (right) and b (down) axes, across the line of sight."""
    distance = float(np.linalg.norm(position))
    sight = position / distance if distance > 0.0 else np.array([0.0, 0.0, 1.0])
    down = np.array([0.0, 1.0, 0.0])
    e1 = _cross(down, sight)
    norm = float(np.linalg.norm(e1))
    if norm < 1e-9:  # straight above or below the head: any horizontal axis will do
        e1, norm = np.array([1.0, 0.0, 0.0]), 1.0
    e1 = e1 / norm
    e2 = _cross(sight, e1)
    return e1, e2


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.cross`` of two 3-vectors with the same float64 operations (multiply, then subtract),
    so the same bits, without its axis handling: 0.2 ms a call, a third of a frame's geometry."""
    a0, a1, a2 = (float(x) for x in a)
    b0, b1, b2 = (float(x) for x in b)
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _blob_texture(config: TargetConfig) -> npt.NDArray[np.float32]:
    """Seeded high-contrast blobs between the dark level and the foreground level."""
    rng = np.random.default_rng(config.texture_seed)
    noise = rng.standard_normal((TEXTURE_PX, TEXTURE_PX)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), TEXTURE_PX / 40.0)
    level = (smooth > 0).astype(np.float32)
    texture = config.dark_dn + (config.foreground_dn - config.dark_dn) * level
    return np.asarray(texture, dtype=np.float32)


def _aruco_texture(config: TargetConfig) -> tuple[npt.NDArray[np.float32], float]:
    """An ArUco marker on a white card with a quiet zone; (texture, marker side / card side)."""
    dictionary_id = getattr(cv2.aruco, config.aruco_dictionary, None)
    if not isinstance(dictionary_id, int):
        raise ValueError(f"unknown ArUco dictionary {config.aruco_dictionary!r} (e.g. DICT_4X4_50)")
    dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id)
    cells = int(dictionary.markerSize) + 2  # data bits plus the black border
    total = cells + 2 * ARUCO_QUIET_MODULES
    cell_px = max(1, TEXTURE_PX // total)
    marker = cv2.aruco.generateImageMarker(dictionary, config.aruco_id, cells * cell_px)
    pad = ARUCO_QUIET_MODULES * cell_px
    card = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    white = card.astype(np.float32) / 255.0
    texture = config.dark_dn + (config.foreground_dn - config.dark_dn) * white
    return np.asarray(texture, dtype=np.float32), cells / total
