"""The scheduler's configuration: timing, burst policy, link and pan/tilt geometry."""

from __future__ import annotations

from dataclasses import dataclass

from dffd.literals import BurstMode, PanTiltMode
from dffd.scheduler.geometry import pixel_offset_to_deg
from dffd.scheduler.wire import PAN_TILT_DRIVE_BYTES, link_time_s


@dataclass(frozen=True, slots=True, kw_only=True)
class SchedulerConfig:
    """Timing, policy and geometry the scheduler needs.

    Built from the service config by :func:`dffd.wiring.scheduler_config`: the fields it sets
    have no defaults here (the config's are the only ones); the rest are the scheduler's own.
    """

    fps: float
    # Exposure duration (s); None = the full frame period (the conservative assumption).
    exposure_s: float | None
    # Frames between exposure and delivery (measured by `dffd calibrate`); only the rate limit of
    # the non-predictive mode and the pan/tilt delay depend on it.
    capture_latency_frames: int
    # Bound on the error of frame timestamps (s): a frame counts as exposed off a focus move only
    # with this much to spare either side; covers capture timestamp jitter and reply transit.
    timing_margin_s: float
    # Burst policy. ``classic``: three settings mid → end → end → mid per burst, then
    # ``burst_every_frames`` tracking frames. ``rolling``: a triangle lo, mid, hi, mid, lo, … with
    # ``max(1, burst_every_frames)`` tracking frames at each pass through the middle; every
    # arrival at an end closes a burst with the previous end and the middle frame between.
    burst_mode: BurstMode
    burst_every_frames: int
    sigma_trigger_m: float | None
    snap_counts: int = 40
    snap_fraction: float = 0.25
    retarget_steps: float = 0.25
    # Focus motor and link timing.
    focus_speed_counts_per_s: float
    focus_tolerance_counts: int = 2
    baudrate: int
    # The camera accepts one command per video field (docs/design.md §6: ~1V, 16.7 ms at 60 Hz).
    command_slot_s: float = 1.0 / 60.0
    initial_focus_counts: int | None = None
    # The side of the focus counts that focuses farther: −1 when lower counts focus farther
    # (VISCA cameras: the EVI-D100's 0x1000 is infinity), +1 otherwise. Before the first depth
    # the bracket over the working range ends at its far end (docs/design.md §5.3).
    far_focus_side: int = -1
    focus_inquiry_interval_s: float = 0.05
    # Pan/tilt.
    pan_tilt_mode: PanTiltMode
    # The camera model's speed tables (deg/s of speed codes 01, 02, …), from the driver's profile
    # (``CameraProfile.pan_speeds_deg_s``/``tilt_speeds_deg_s``): the commanded rates and the
    # head model's dead reckoning are in these.
    pan_speeds_deg_s: tuple[float, ...]
    tilt_speeds_deg_s: tuple[float, ...]
    focal_length_mm: float
    pixel_pitch_mm: float
    frame_size: tuple[int, int]
    pan_tilt_gain_per_s: float  # commanded deg/s per degree of error
    pan_tilt_feedforward: bool  # add the target's filtered angular velocity
    pan_tilt_velocity_tau_s: float = 0.3  # time constant of that velocity filter
    # Feed-forward from the 3D tracker (docs/tracking3d.md, "Pan/tilt feed-forward"): the
    # target's angular velocity is the tracker's (its predicted direction's rate) instead of the
    # filtered centroid differences, whenever the tracker has a fresh track. Off by default.
    pan_tilt_track_feedforward: bool = False
    pan_tilt_lost_s: float  # no centroid for this long: the target is lost → search
    # Search after a loss: keep driving towards the target's extrapolated direction (its last
    # direction plus its filtered angular velocity times the time since) for this long, then
    # return to the last direction it was seen in and hold there (0: hold at once).
    pan_tilt_search_s: float
    # Consecutive frames with a contour before the core's burst plans are followed: bursts (long
    # focus travel, transit frames) start only once the contour is stable (0: no such gate).
    acquire_stable_frames: int
    # Hysteresis band (deg): a correction starts when the error projected to the end of the free
    # window exceeds it, and runs until that error is cancelled.
    pan_tilt_deadband_deg: float
    # Cap on |correction speed − ω̂| (deg/s) unless the proportional gain asks for more: the core's
    # tracker predicts image motion at constant velocity and searches ±12 px along its normals
    # (12 px × 30 fps ≈ 3.3°/s at f = 31 mm, 5 µm pixels).
    pan_tilt_max_correction_deg_s: float
    # Aim of a correction: the error left when the quiet speed resumes is (q − ω̂)·lead, so the
    # drift through the measured frames carries it across zero (~half a rolling-bracket cycle).
    pan_tilt_lead_s: float = 0.2
    # Correction horizon while no bursts run (acquisition): no measured exposures to keep clear.
    pan_tilt_horizon_s: float = 0.3
    # Position resolution of the head (deg): EVI-D100 14.4 counts/°. Inquiry replies are
    # quantised to it; the model is kept within it rather than snapped.
    pan_tilt_resolution_deg: float = 1.0 / 14.4
    pan_tilt_min_interval_s: float
    pan_tilt_poll_interval_s: float = 0.25
    absolute_speed_index: int = 0x10
    # Search sweep (dffd.scheduler.search). Automatic acquisition that has seen no target for
    # search_after_s sweeps the head over its pan/tilt range (the camera model's); None: never
    # (the scheduler's own default: the bench and the tests; the service sets it).
    search_after_s: float | None = None
    # A pass that found nothing: hold where it began for this long, then sweep again.
    search_retry_s: float = 60.0
    # Dwell at each view: the frames exposed after the head stopped there. The core searches the
    # whole frame at least every 5th frame while it acquires after a loss (reacquire_every_frames;
    # every frame before a first sighting): 0.3 s holds 9 frames at 30 fps, two of those searches
    # or more, and the centroid of a hit comes back (1-2 frames of latency) before the next move.
    search_dwell_s: float = 0.3
    # Overlap of neighbouring views, a fraction of the field of view: a target no wider than this
    # is wholly inside some view (the detector ignores outlines that touch the frame's edge).
    search_overlap: float = 0.2
    pan_range_deg: tuple[float, float] | None = None  # the head's range (None: no sweep)
    tilt_range_deg: tuple[float, float] | None = None
    pan_sign: int = 1  # +1: image x to the right is positive pan
    tilt_sign: int = 1  # +1: image y upwards is positive tilt

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"fps must be > 0 (got {self.fps})")
        if self.exposure_s is not None and not 0 < self.exposure_s <= 1.0 / self.fps:
            raise ValueError(f"exposure_s must be in (0, 1/fps] (got {self.exposure_s})")
        if self.burst_every_frames < 0:
            raise ValueError(f"burst_every_frames must be >= 0 (got {self.burst_every_frames})")
        if self.burst_mode not in ("rolling", "classic"):
            raise ValueError(f"burst_mode must be 'rolling' or 'classic' (got {self.burst_mode!r})")
        if self.focus_speed_counts_per_s <= 0:
            raise ValueError("focus_speed_counts_per_s must be > 0")
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be > 0 (got {self.baudrate})")
        if self.far_focus_side not in (1, -1):
            raise ValueError(f"far_focus_side must be +1 or -1 (got {self.far_focus_side})")
        if self.pan_sign not in (1, -1) or self.tilt_sign not in (1, -1):
            raise ValueError("pan_sign and tilt_sign must be +1 or -1")
        if self.pan_tilt_search_s < 0 or self.pan_tilt_lost_s < 0:
            raise ValueError("pan_tilt_lost_s and pan_tilt_search_s must be >= 0")
        if self.search_after_s is not None and self.search_after_s < 0:
            raise ValueError(f"search_after_s must be >= 0 (got {self.search_after_s})")
        if self.search_retry_s < 0 or self.search_dwell_s < 0:
            raise ValueError("search_retry_s and search_dwell_s must be >= 0")
        if not 0.0 <= self.search_overlap < 1.0:
            raise ValueError(f"search_overlap must be in [0, 1) (got {self.search_overlap})")
        for name in ("pan_range_deg", "tilt_range_deg"):
            span = getattr(self, name)
            if span is not None and not span[0] < span[1]:
                raise ValueError(f"{name} must be (low, high) with low < high (got {span!r})")
        if self.acquire_stable_frames < 0:
            raise ValueError("acquire_stable_frames must be >= 0")
        for name in ("pan_speeds_deg_s", "tilt_speeds_deg_s"):
            table = getattr(self, name)
            if not table or any(v <= 0 for v in table):
                raise ValueError(f"{name} must list positive speeds (got {table!r})")

    @property
    def period_s(self) -> float:
        """Nominal frame period."""
        return 1.0 / self.fps

    @property
    def guard_s(self) -> float:
        """Scheduling guard around a claimed exposure: the tag check's margin plus the
        prediction's own error bound (both ``timing_margin_s``), so a claimed frame passes the
        check even when its timestamp arrives off by the margin."""
        return 2.0 * self.timing_margin_s

    @property
    def exposure(self) -> float:
        """Exposure duration used for tagging (s)."""
        return self.exposure_s if self.exposure_s is not None else self.period_s

    @property
    def pan_tilt_latency_s(self) -> float:
        """Longest time from writing a Pan-tiltDrive to the motors changing: its bytes, then up
        to one camera command slot (the camera takes commands at field boundaries), plus the
        timing margin."""
        return (
            link_time_s(PAN_TILT_DRIVE_BYTES, self.baudrate)
            + self.command_slot_s
            + self.timing_margin_s
        )

    @property
    def pan_tilt_model_delay_s(self) -> float:
        """Mean time from writing a pan/tilt command to the motors changing (the model's)."""
        return link_time_s(PAN_TILT_DRIVE_BYTES, self.baudrate) + self.command_slot_s / 2.0

    @property
    def pan_tilt_emergency_deg(self) -> float:
        """Error (deg) corrected at once, measured frames or not: half-way to the nearer frame
        edge."""
        half = min(self.frame_size) / 4.0
        return pixel_offset_to_deg(half, self.focal_length_mm, self.pixel_pitch_mm)
