"""Exposure clock: predicts the exposure windows of frames in flight and of future frames.

Exposures are periodic; from the delivered frames' timestamps a phase-locked loop estimates the
mid-time of the latest exposure and the period, so the scheduler can claim an exposure for a burst
slot before its frame is delivered (the capture latency then costs nothing in steady state).
"""

from __future__ import annotations

import math

# Gains of the exposure-clock tracker (per delivered frame): the phase follows a timestamp
# step within ~5 frames, the period within ~100; jitter is averaged over as many frames.
PHASE_GAIN = 0.2
PERIOD_GAIN = 0.01
# Float rounding allowance when comparing times (s); far below any physical timing.
TIME_EPS_S = 1e-7


class ExposureClock:
    """Phase-locked estimate of the exposure clock from delivered frame timestamps."""

    def __init__(self, period_s: float, exposure_s: float) -> None:
        self.t_ref: float | None = None  # the last delivered exposure mid-time
        self.period = period_s  # estimated from delivered timestamps
        self._nominal = period_s
        self._exposure = exposure_s
        self._last_index: int | None = None

    def update(self, index: int, t: float) -> None:
        """Frame ``index`` exposed around mid-time ``t`` was delivered.

        Smooths timestamp jitter out of the predictions (a single late timestamp must not shift
        every future claim).
        """
        if self.t_ref is None or self._last_index is None or index <= self._last_index:
            self.t_ref, self._last_index = t, index
            return
        steps = index - self._last_index
        predicted = self.t_ref + steps * self.period
        innovation = t - predicted
        if abs(innovation) < self.period / 2.0:
            self.t_ref = predicted + PHASE_GAIN * innovation
            period = self.period + PERIOD_GAIN * innovation / steps
            nominal = self._nominal
            self.period = min(max(period, 0.8 * nominal), 1.25 * nominal)
        else:
            self.t_ref = t  # a stall or a clock step: re-lock on this frame
        self._last_index = index

    def first_mid_starting_after(self, t: float) -> float:
        """Mid-time of the first predicted exposure that starts at or after ``t``."""
        assert self.t_ref is not None
        half = self._exposure / 2.0
        k = math.ceil((t + half - self.t_ref) / self.period - 1e-9)
        return self.t_ref + k * self.period

    def last_mid_ending_before(self, t: float) -> float:
        """Mid-time of the last predicted exposure that ends at or before ``t``."""
        assert self.t_ref is not None
        half = self._exposure / 2.0
        k = math.floor((t - half - self.t_ref) / self.period + 1e-9)
        return self.t_ref + k * self.period

    def next_mid_after(self, mid: float) -> float:
        """Mid-time of the predicted exposure after the one at ``mid`` (−inf: none tagged yet)."""
        if mid == -math.inf or self.t_ref is None:
            return -math.inf
        k = math.floor((mid - self.t_ref) / self.period + 0.5) + 1
        return self.t_ref + k * self.period

    def end_of(self, mid: float) -> float:
        """End of the exposure around mid-time ``mid``."""
        return mid + self._exposure / 2.0
