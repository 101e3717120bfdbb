"""Camera models: ranges, counts per degree, speed tables, timings and VersionInq identities.

A :class:`CameraProfile` converts user units to VISCA values and checks them *before* anything is
sent (``ValueError`` naming the value, its range and the model). ``camera.model`` names one;
:func:`profile_for_version` finds the one a camera identifies as, so the driver can use the
camera's real limits and say when the configuration names another model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.visca.codec_framing import check_range

# VersionInq vendor IDs of Sony: 0x0001 in the EVI/SRG technical manuals, 0x0020 in the FCB
# block-camera manuals (and libvisca); both are accepted.
SONY = 0x0001
SONY_FCB = 0x0020


class SpeedCode(int):
    """A raw VISCA pan/tilt speed code (01…18), as opposed to a speed in deg/s."""

    __slots__ = ()


@dataclass(frozen=True, slots=True)
class CameraProfile:
    """What differs between camera models: ranges, counts per degree, speed tables, timings."""

    name: str
    pan_range_deg: tuple[float, float]
    tilt_range_deg: tuple[float, float]
    pan_counts_per_deg: float
    tilt_counts_per_deg: float
    pan_speeds_deg_s: tuple[float, ...]  # deg/s of speed codes 01, 02, …
    tilt_speeds_deg_s: tuple[float, ...]
    focus_range: tuple[int, int]  # far end … near end, counts
    zoom_range: tuple[int, int]  # wide … tele, counts
    focus_full_travel_s: float  # worst-case Focus Direct end to end
    zoom_full_travel_s: float  # worst-case Zoom Direct end to end
    home_speed_deg_s: float  # speed of Home (the camera's own choice)
    focus_completion_early: bool = False  # Completion before the lens has stopped
    focus_settle_tolerance_counts: int = 0
    # VersionInq identity: (vendor, model) pairs this camera answers (empty: not identifiable).
    identities: tuple[tuple[int, int], ...] = ()

    @property
    def key(self) -> str:
        """The ``camera.model`` value that names this profile (e.g. ``"evi-d100"``)."""
        return self.name.lower()

    def check_focus(self, counts: int) -> int:
        """``counts`` if within the focus range, else ValueError naming the range and model."""
        return _check_counts("focus counts", counts, self.focus_range, self.name)

    def check_zoom(self, counts: int) -> int:
        """``counts`` if within the zoom range, else ValueError naming the range and model."""
        return _check_counts("zoom counts", counts, self.zoom_range, self.name)

    @property
    def max_pan_speed_code(self) -> int:
        """Highest pan speed code."""
        return len(self.pan_speeds_deg_s)

    @property
    def max_tilt_speed_code(self) -> int:
        """Highest tilt speed code."""
        return len(self.tilt_speeds_deg_s)

    def pan_to_counts(self, pan_deg: float, field: str = "pan_deg") -> int:
        """Absolute pan angle → position counts (ValueError outside the range)."""
        return round(
            check_degrees(field, pan_deg, self.pan_range_deg, self.name) * self.pan_counts_per_deg
        )

    def tilt_to_counts(self, tilt_deg: float, field: str = "tilt_deg") -> int:
        """Absolute tilt angle → position counts (ValueError outside the range)."""
        return round(
            check_degrees(field, tilt_deg, self.tilt_range_deg, self.name)
            * self.tilt_counts_per_deg
        )

    def pan_speed_code(self, speed: float | SpeedCode | None, field: str = "speed") -> int:
        """A pan speed (deg/s, or a SpeedCode; None = fastest) → speed code."""
        return _speed_code(speed, self.pan_speeds_deg_s, field, self.name)

    def tilt_speed_code(self, speed: float | SpeedCode | None, field: str = "tilt_speed") -> int:
        """A tilt speed → speed code; a speed beyond the tilt table runs at the fastest tilt."""
        if speed is not None and not isinstance(speed, SpeedCode):
            _check_positive(field, speed)
            speed = min(float(speed), self.tilt_speeds_deg_s[-1])
        return _speed_code(speed, self.tilt_speeds_deg_s, field, self.name)


# EVI-D100 (design.md §6; Sony EVI-D100 technical manual): pan ±100° = 0xFA60…0x05A0, tilt ±25° =
# 0xFE98…0x0168, 14.4 counts/°; pan codes 01…18, tilt 01…14 share one table.
_D100_SPEEDS = (
    2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0,
    27.0, 34.0, 42.0, 52.0, 65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0,
)  # fmt: skip
EVI_D100 = CameraProfile(
    name="EVI-D100",
    pan_range_deg=(-100.0, 100.0),
    tilt_range_deg=(-25.0, 25.0),
    pan_counts_per_deg=14.4,
    tilt_counts_per_deg=14.4,
    pan_speeds_deg_s=_D100_SPEEDS,
    tilt_speeds_deg_s=_D100_SPEEDS[:0x14],
    focus_range=(0x1000, 0x8400),
    zoom_range=(0x0000, 0x4000),
    focus_full_travel_s=2.0,  # Focus Direct ~2 s worst case end to end (issue 2)
    zoom_full_travel_s=2.5,
    home_speed_deg_s=300.0,
    identities=((SONY, 0x040D), (SONY_FCB, 0x040D)),
)

# EVI-D70 (Sony EVI-D70 technical manual, "Pan/tilt position" in the D30/D31 and D70-mode
# tables): pan −170…+170° = 0xF725…0x08DB (±2267), tilt −30…+90° = 0xFE70…0x04B0 (−400…+1200),
# i.e. 13.33 counts/° on both axes; focus 0x1000 (far) … 0xC000 (near, 10 cm); optical zoom
# 0x0000…0x4000 (digital to 0x7AC0 is not used for depth from focus). Speed codes: pan 01…18,
# tilt 01…17, maxima 100 °/s pan and 90 °/s tilt (spec sheet). ASSUMPTION: the per-code table
# was not found in the sources available; it is taken log-spaced from 2 °/s (as the D100's
# code 01) to those maxima. Verify on hardware before relying on deg/s for this model.
EVI_D70 = CameraProfile(
    name="EVI-D70",
    pan_range_deg=(-170.0, 170.0),
    tilt_range_deg=(-30.0, 90.0),
    pan_counts_per_deg=2267 / 170,
    tilt_counts_per_deg=1200 / 90,
    pan_speeds_deg_s=tuple(round(2.0 * (100.0 / 2.0) ** (i / 23), 2) for i in range(24)),
    tilt_speeds_deg_s=tuple(round(2.0 * (90.0 / 2.0) ** (i / 22), 2) for i in range(23)),
    focus_range=(0x1000, 0xC000),
    zoom_range=(0x0000, 0x4000),
    focus_full_travel_s=2.5,
    zoom_full_travel_s=2.5,
    home_speed_deg_s=100.0,
    identities=((SONY, 0x040E), (SONY_FCB, 0x040E)),
)

# SRG-300-like VISCA-over-IP head. Identity from the SRG-300SE/301SE technical manual
# (CAM_VersionInq: vendor 0001 Sony, model 0516). ASSUMPTIONS (spec-sheet level, not from a
# position table): pan ±170°, tilt −20…+90°, pan 1.1–100 °/s and tilt 1.1–90 °/s over 24/23
# log-spaced codes, 13.33 counts/° as the D70, focus 0x1000 (far) … 0xF000 (near), optical zoom
# 0x0000…0x4000 (30×). Verify against the camera's manual before relying on the numbers.
SRG_300 = CameraProfile(
    name="SRG-300",
    pan_range_deg=(-170.0, 170.0),
    tilt_range_deg=(-20.0, 90.0),
    pan_counts_per_deg=2267 / 170,
    tilt_counts_per_deg=1200 / 90,
    pan_speeds_deg_s=tuple(round(1.1 * (100.0 / 1.1) ** (i / 23), 2) for i in range(24)),
    tilt_speeds_deg_s=tuple(round(1.1 * (90.0 / 1.1) ** (i / 22), 2) for i in range(23)),
    focus_range=(0x1000, 0xF000),
    zoom_range=(0x0000, 0x4000),
    focus_full_travel_s=2.5,
    zoom_full_travel_s=3.0,
    home_speed_deg_s=100.0,
    identities=((SONY, 0x0516),),
)

PROFILES: dict[str, CameraProfile] = {p.key: p for p in (EVI_D100, EVI_D70, SRG_300)}


def profile_for_version(vendor: int, model: int) -> CameraProfile | None:
    """The profile whose camera answers VersionInq with ``(vendor, model)`` (None: unknown)."""
    for profile in PROFILES.values():
        if (vendor, model) in profile.identities:
            return profile
    return None


def profile_for(model: str) -> CameraProfile:
    """The profile of ``model`` (case-insensitive, e.g. ``"EVI-D100"``); ValueError lists them."""
    try:
        return PROFILES[model.strip().lower()]
    except KeyError:
        known = ", ".join(p.name for p in PROFILES.values())
        raise ValueError(f"unknown camera model {model!r}; known models: {known}") from None


__all__ = [
    "EVI_D70",
    "EVI_D100",
    "PROFILES",
    "SONY",
    "SONY_FCB",
    "SRG_300",
    "CameraProfile",
    "SpeedCode",
    "check_degrees",
    "nearest_speed_code",
    "profile_for",
    "profile_for_version",
]


# --------------------------------------------------------------------------------------------
# Helpers (checks shared with the camera API)
# --------------------------------------------------------------------------------------------


def check_degrees(field: str, value: float, limits: tuple[float, float], model: str) -> float:
    low, high = limits
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(
            f"{field} must be a finite number of degrees in [{low}, {high}], got {value!r}"
        )
    if not low <= value <= high:
        raise ValueError(f"{field} = {value}° is out of range [{low}°, {high}°] for the {model}")
    return float(value)


def _check_counts(field: str, value: int, limits: tuple[int, int], model: str) -> int:
    low, high = limits
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{field} must be an integer in [{low}, {high}], got {value!r}")
    if not low <= value <= high:
        raise ValueError(
            f"{field} = {value} (0x{value:X}) is out of range [0x{low:X}, 0x{high:X}] for the "
            f"{model}"
        )
    return value


def _check_positive(field: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{field} must be a finite speed in deg/s, got {value!r}")
    if value <= 0:
        raise ValueError(f"{field} = {value} deg/s must be positive")


def _speed_code(
    speed: float | SpeedCode | None, table: tuple[float, ...], field: str, model: str
) -> int:
    if speed is None:
        return len(table)
    if isinstance(speed, SpeedCode):
        return check_range(f"{field} code", int(speed), 1, len(table))
    _check_positive(field, speed)
    if speed > table[-1]:
        raise ValueError(
            f"{field} = {speed} deg/s is out of range (0, {table[-1]}] deg/s for the {model}"
        )
    return nearest_speed_code(float(speed), table)


def nearest_speed_code(speed: float, table: tuple[float, ...]) -> int:
    """Speed code (≥ 01) nearest ``speed`` in ratio (the speed tables are geometric)."""
    target = math.log(speed)
    best = min(range(len(table)), key=lambda i: abs(math.log(table[i]) - target))
    return best + 1
