"""What one bench session produces, whatever ran it (lock-step, real time, or hardware).

The runners fill these records; :mod:`hil.report` turns a list of them (cases × seeds) into
``report.json`` and the plots. Everything here is plain data: times are the run's clock in
seconds, depths in metres, and every estimate is paired with the ground truth at the instant it
refers to.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from hil.track3d import Track3DScore

FloatArray = npt.NDArray[np.float64]


@dataclass
class Series:
    """Values of one quantity over time with the truth each should equal (NaN when unknown) and
    the σ published with each value (NaN when none)."""

    t: list[float] = field(default_factory=list)
    value: list[float] = field(default_factory=list)
    truth: list[float] = field(default_factory=list)
    sigma: list[float] = field(default_factory=list)

    def add(
        self, t: float, value: float, truth: float = float("nan"), sigma: float | None = None
    ) -> None:
        """Append one sample (``sigma``: the σ published with it, if any)."""
        self.t.append(t)
        self.value.append(value)
        self.truth.append(truth)
        self.sigma.append(float("nan") if sigma is None else sigma)

    def __len__(self) -> int:
        return len(self.t)

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(t, value, truth)`` as float arrays."""
        return (
            np.asarray(self.t, dtype=np.float64),
            np.asarray(self.value, dtype=np.float64),
            np.asarray(self.truth, dtype=np.float64),
        )

    def sigmas(self) -> FloatArray:
        """The published σ of every sample (NaN where none was published)."""
        return np.asarray(self.sigma, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class BurstRecord:
    """One depth measurement attempt: the focus settings, the costs and the fit."""

    t: float  # exposure mid-time of the burst's middle frame
    v0_mm: tuple[float, ...]
    cost: tuple[float, ...]
    accepted: bool
    reason: str
    v_hat_mm: float | None
    coeffs: tuple[float, float, float] | None  # g = a v0² + b v0 + c, when the core reports it
    z_m: float | None
    truth_z_m: float
    truth_v_mm: float | None  # the sharp setting for the true depth (bench-side, from the lens)


@dataclass
class RunResult:
    """One session (one case, one seed) of a scenario."""

    scenario: str
    case: str
    seed: int
    mode: str  # "fast" | "realtime" | "hardware"
    duration_s: float
    settle_s: float
    t_start: float = 0.0
    best: str = "lpv"
    estimates: dict[str, Series] = field(default_factory=dict)  # incl. "measured" (raw z_m)
    baselines: dict[str, Series] = field(default_factory=dict)
    beta: Series = field(default_factory=Series)  # CF2's bias estimate β̂ (m/s)
    size: Series = field(default_factory=Series)  # R̂ (m), truth = the real size
    r_px: Series = field(default_factory=Series)  # tracked r on track frames, truth r from the sim
    truth_depth: Series = field(default_factory=Series)  # true z per track frame (for binning)
    bursts: list[BurstRecord] = field(default_factory=list)
    frames: int = 0
    frames_by_role: dict[str, int] = field(default_factory=dict)
    estimate_frames: int = 0  # frames the core answered with an estimate (any role)
    # of those, the estimates whose depths the first-depth gate held back (not scored)
    withheld: int = 0
    depth_limit_hz: float | None = None
    full_sweep_depth_hz: float | None = None
    core_cpu_s: list[float] = field(default_factory=list)  # per processed frame
    latency_s: list[float] = field(default_factory=list)  # exposure → MQTT (real time only)
    wall_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    track3d: Track3DScore | None = None  # the 3D trackers against the 3D truth (fast mode)

    def series(self, name: str) -> Series:
        """The estimate series ``name``, created on first use."""
        return self.estimates.setdefault(name, Series())

    def baseline(self, name: str) -> Series:
        """The baseline series ``name``, created on first use."""
        return self.baselines.setdefault(name, Series())

    @property
    def accepted_bursts(self) -> int:
        """Bursts whose fit was accepted (depth measurements)."""
        return sum(1 for b in self.bursts if b.accepted)

    @property
    def depth_hz(self) -> float:
        """Accepted depth measurements per second of scenario time."""
        return self.accepted_bursts / self.duration_s if self.duration_s > 0 else 0.0
