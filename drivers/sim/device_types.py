"""The simulated VISCA camera's settings and outputs: what a transport configures and gets back.

The device's own constants (field period, byte time, default motor speeds, power-on time, ROM
version), its configuration (:class:`DeviceConfig`), the bytes it emits (:class:`Emission`) and
its counters (:class:`DeviceStats`). The camera's facts (end stops, counts per degree, speed
tables, focus and zoom ranges, VersionInq identity) are its camera model's,
:mod:`drivers.sim.models`. The device that takes and gives them is :mod:`drivers.sim.device`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.sim.models import EVI_D100 as SIM_EVI_D100
from drivers.sim.models import SimModel
from drivers.visca import codec_framing

# ---- device constants (EVI-D100-like, design.md §6) --------------------------------------------

FIELD_PERIOD_S = 1.0 / 60.0  # NTSC field: the camera handles at most one message per field
BITS_PER_BYTE = 10  # 8N1 on the wire: start bit, 8 data bits, stop bit
# Assumed motor speeds (no datasheet figure): focus sweeps the EVI-D100's full range in about
# 1.5 s, zoom goes wide → tele in about 2 s, both typical of the EVI-D100 generation. They are
# the device's, not the camera model's: another model keeps these counts per second.
DEFAULT_FOCUS_SPEED_COUNTS_S = (SIM_EVI_D100.focus_range[1] - SIM_EVI_D100.focus_range[0]) / 1.5
DEFAULT_ZOOM_SPEED_COUNTS_S = (SIM_EVI_D100.zoom_range[1] - SIM_EVI_D100.zoom_range[0]) / 2.0
DEFAULT_POWER_ON_S = 0.1  # standby → on (real cameras take seconds; short keeps tests fast)
DEFAULT_ROM = 0x0200  # VersionInq ROM version (vendor and model code are the camera model's)


@dataclass(frozen=True, slots=True)
class DeviceConfig:
    """How the simulated camera behaves; defaults are an EVI-D100 at 9600 baud, no pacing."""

    address: int = 1  # position in the daisy chain: address before Address Set; see Address Set
    baud: int = 9600
    pace: bool = False  # model the wire time of every byte at ``baud`` (10 bits per byte)
    field_period_s: float = FIELD_PERIOD_S
    focus_speed_counts_s: float = DEFAULT_FOCUS_SPEED_COUNTS_S  # Focus Direct / One Push
    zoom_speed_counts_s: float = DEFAULT_ZOOM_SPEED_COUNTS_S  # Zoom Direct
    focus_drive_standard: int = 4  # Focus Far/Near without a speed drive at variable speed p=4
    power_on_s: float = DEFAULT_POWER_ON_S
    autofocus_at_power_up: bool = True  # real cameras come up in AF: drivers must set manual
    network_change_at_power_up: bool = True
    reply_from_a0: bool = False  # firmware quirk (design.md §6): replies carry header A0, not 90
    # Emulator quirk: the broadcast IF_Clear clears the sockets but is not echoed (the spec
    # echoes it); a controller must fall back to each camera's own IF_Clear.
    echo_if_clear_broadcast: bool = True
    camera: SimModel = SIM_EVI_D100  # limits, speeds and identity (drivers/sim/models.py)
    vendor: int | None = None  # VersionInq vendor; None: the camera model's
    model: int | None = None  # VersionInq model code; None: the camera model's
    rom: int = DEFAULT_ROM
    sockets: int = 2

    def __post_init__(self) -> None:
        codec_framing.check_range("address", self.address, 1, 7)
        if self.baud <= 0 or self.field_period_s <= 0:
            raise ValueError("baud and field_period_s must be positive")
        if self.focus_speed_counts_s <= 0 or self.zoom_speed_counts_s <= 0:
            raise ValueError("focus and zoom speeds must be positive (counts per second)")
        codec_framing.check_range("focus_drive_standard", self.focus_drive_standard, 0, 7)
        if self.power_on_s < 0:
            raise ValueError("power_on_s must not be negative")

    @property
    def byte_time_s(self) -> float:
        """Wire time of one byte at ``baud`` (8N1)."""
        return BITS_PER_BYTE / self.baud

    def focus_drive_speed(self, p: int) -> float:
        """Focus Far/Near speed in counts/s for variable speed ``p`` (0 slowest … 7 = Direct)."""
        return self.focus_speed_counts_s * (p + 1) / 8


@dataclass(frozen=True, slots=True)
class Emission:
    """Bytes the camera puts on the wire, and when their last byte has left it."""

    t: float
    data: bytes


@dataclass(slots=True)
class DeviceStats:
    """Counters for tests and the benchmark."""

    packets_in: int = 0
    packets_out: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    errors_out: dict[int, int] = field(default_factory=dict)
    input_overflow: int = 0
    ignored: int = 0  # packets for another address or not from a controller
    lost_completions: int = 0
