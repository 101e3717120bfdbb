"""Camera models the simulated VISCA device can be: limits, speeds and VersionInq identity.

Written from the cameras' documents, independently of the driver's own profiles
(``drivers/visca/profiles.py``), so a wrong number in one is caught by the other in the
camera-API tests. Select one with ``DeviceConfig(camera=sim_model("evi-d70"))`` or
``dffd sim-camera --model evi-d70``. The renderer's lens (``drivers/sim/data``) stays the
EVI-D100's: a model changes the VISCA device, not the optics.
"""

from __future__ import annotations

from dataclasses import dataclass

VENDOR_SONY = 0x0001  # Sony's vendor ID in the EVI/SRG technical manuals' CAM_VersionInq


@dataclass(frozen=True, slots=True)
class SimModel:
    """What the simulated device enforces and reports for one camera model."""

    name: str
    vendor: int
    model: int  # VersionInq model code
    pan_counts_per_deg: float
    tilt_counts_per_deg: float
    pan_limits_deg: tuple[float, float]
    tilt_limits_deg: tuple[float, float]
    pan_speeds_deg_s: tuple[float, ...]  # deg/s of speed codes 01, 02, …
    tilt_speeds_deg_s: tuple[float, ...]
    focus_range: tuple[int, int]  # far end … near end, counts
    zoom_range: tuple[int, int]  # wide … tele (optical), counts

    @property
    def max_pan_speed_code(self) -> int:
        """Highest pan speed code."""
        return len(self.pan_speeds_deg_s)

    @property
    def max_tilt_speed_code(self) -> int:
        """Highest tilt speed code."""
        return len(self.tilt_speeds_deg_s)

    @property
    def pan_limit_counts(self) -> tuple[int, int]:
        """Pan end stops in position counts."""
        low, high = self.pan_limits_deg
        return round(low * self.pan_counts_per_deg), round(high * self.pan_counts_per_deg)

    @property
    def tilt_limit_counts(self) -> tuple[int, int]:
        """Tilt end stops in position counts."""
        low, high = self.tilt_limits_deg
        return round(low * self.tilt_counts_per_deg), round(high * self.tilt_counts_per_deg)


# EVI-D100 (technical manual): pan ±100° = 0xFA60…0x05A0, tilt ±25° = 0xFE98…0x0168 (14.4
# counts/°); speed codes 01…18 pan, 01…14 tilt on one table (the manual's "Pan/tilt speed" page,
# D30/31 mode off); focus 0x1000 far … 0x8400 near; optical zoom 0x0000…0x4000.
_D100_SPEEDS = (
    2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0,
    27.0, 34.0, 42.0, 52.0, 65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0,
)  # fmt: skip
EVI_D100 = SimModel(
    name="EVI-D100",
    vendor=VENDOR_SONY,
    model=0x040D,
    pan_counts_per_deg=14.4,
    tilt_counts_per_deg=14.4,
    pan_limits_deg=(-100.0, 100.0),
    tilt_limits_deg=(-25.0, 25.0),
    pan_speeds_deg_s=_D100_SPEEDS,
    tilt_speeds_deg_s=_D100_SPEEDS[:0x14],
    focus_range=(0x1000, 0x8400),
    zoom_range=(0x0000, 0x4000),
)

# EVI-D70 (technical manual, D70-mode position tables): pan −170…+170° = 0xF725…0x08DB (2267
# counts for 170°), tilt −30…+90° = 0xFE70…0x04B0 (−400…+1200); pan codes 01…18 up to 100 °/s,
# tilt 01…17 up to 90 °/s (spec sheet). The per-code values are not in the sources at hand:
# ASSUMED log-spaced from 2 °/s. Focus 0x1000 … 0xC000 (10 cm near limit); optical zoom
# 0x0000…0x4000.
EVI_D70 = SimModel(
    name="EVI-D70",
    vendor=VENDOR_SONY,
    model=0x040E,
    pan_counts_per_deg=2267 / 170,
    tilt_counts_per_deg=1200 / 90,
    pan_limits_deg=(-170.0, 170.0),
    tilt_limits_deg=(-30.0, 90.0),
    pan_speeds_deg_s=tuple(2.0 * (100.0 / 2.0) ** (i / 23) for i in range(24)),
    tilt_speeds_deg_s=tuple(2.0 * (90.0 / 2.0) ** (i / 22) for i in range(23)),
    focus_range=(0x1000, 0xC000),
    zoom_range=(0x0000, 0x4000),
)

# SRG-300-like VISCA-over-IP head. Identity from the SRG-300SE/301SE technical manual's
# CAM_VersionInq (vendor 0001 Sony, model 0516). Limits ASSUMED at spec-sheet level: pan ±170°,
# tilt −20…+90°, pan up to 100 °/s and tilt up to 90 °/s (log-spaced codes from 1.1 °/s), the
# D70's 13.33 counts/°, focus 0x1000 … 0xF000, optical zoom (30×) 0x0000…0x4000.
SRG_300 = SimModel(
    name="SRG-300",
    vendor=VENDOR_SONY,
    model=0x0516,
    pan_counts_per_deg=2267 / 170,
    tilt_counts_per_deg=1200 / 90,
    pan_limits_deg=(-170.0, 170.0),
    tilt_limits_deg=(-20.0, 90.0),
    pan_speeds_deg_s=tuple(1.1 * (100.0 / 1.1) ** (i / 23) for i in range(24)),
    tilt_speeds_deg_s=tuple(1.1 * (90.0 / 1.1) ** (i / 22) for i in range(23)),
    focus_range=(0x1000, 0xF000),
    zoom_range=(0x0000, 0x4000),
)

SIM_MODELS: dict[str, SimModel] = {m.name.lower(): m for m in (EVI_D100, EVI_D70, SRG_300)}


def sim_model(name: str) -> SimModel:
    """The model called ``name`` (case-insensitive); ValueError lists the known ones."""
    try:
        return SIM_MODELS[name.strip().lower()]
    except KeyError:
        known = ", ".join(SIM_MODELS)
        raise ValueError(f"unknown simulated camera model {name!r}; known: {known}") from None


__all__ = ["EVI_D70", "EVI_D100", "SIM_MODELS", "SRG_300", "VENDOR_SONY", "SimModel", "sim_model"]
