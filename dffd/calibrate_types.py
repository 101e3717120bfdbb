"""The data ``dffd calibrate``'s procedure hands its fits: a depth point, the optics a table is
fitted for, and the procedure's error.

A :class:`DepthPoint` is the sharpest setting found for one known depth
(:func:`dffd.calibrate_procedure.sharpest`); the table fit reads it again where the estimator's
closed loop settles and combines repeated sweeps of one depth into one
(:mod:`dffd.calibrate_fit`). Split from :mod:`dffd.calibrate_fit`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol


class CalibrationError(RuntimeError):
    """No sharp setting found (target not found, flat cost, …) or no monotone table fitted."""


@dataclass(frozen=True, slots=True)
class DepthPoint:
    """The sharpest focus setting found for one known depth."""

    z_m: float
    counts: int
    v_mm: float
    cost_min: float
    counts_exact: float = math.nan  # the vertex before rounding (NaN: ``counts``)
    sigma_counts: float = math.nan  # its σ from the fit (NaN: unknown)
    # the fine sweep: settings (counts), mean cost, σ of the mean (for the refit in v)
    sweep: tuple[tuple[float, float, float], ...] = ()
    n_sweeps: int = 1  # sweeps of this depth combined into this point (combine_sweeps)
    spread_counts: float = math.nan  # their vertices' standard deviation (NaN: one sweep)
    sweeps_chi2: float = math.nan  # their χ² per degree of freedom about the mean (NaN: one)
    # how the vertex was read: "least squares" (fit_vertex), "closed loop" (the burst bracket's
    # fixed point) or "closed loop, pinned" (the bracket shifted at an end of the focus range)
    rule: str = "least squares"
    # a bracket end stands for v ∓ h of the sweep's depth; the depth the target was placed at
    target_m: float = math.nan  # NaN: z_m itself
    # a bracket's level (rule "bracket level"): the counts of the settled bracket's other end;
    # the table's mean v at ``at`` and ``pair_at`` is the depth's v (``z_m``: the depth of the
    # mean focus power that gives it). NaN: a point, the table's v at ``at`` is ``v_mm``.
    pair_at: float = math.nan

    @property
    def placed_m(self) -> float:
        """The depth the target was placed at for this sweep."""
        return self.z_m if math.isnan(self.target_m) else self.target_m

    @property
    def at(self) -> float:
        """The sharpest counts, unrounded."""
        return self.counts if math.isnan(self.counts_exact) else self.counts_exact

    @property
    def other(self) -> float:
        """The bracket's other end for a level, else ``at`` (the constraint's second setting)."""
        return self.at if math.isnan(self.pair_at) else self.pair_at


class FocusOptics(Protocol):
    """What a table is fitted for: the optics at a fixed zoom and the focus range."""

    focal_length_mm: float
    pixel_pitch_mm: float
    zoom_counts: int | None
    focus_range: tuple[int, int]  # far end … near end, counts
