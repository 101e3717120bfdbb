"""The focus-sweep baselines' own focus policies in the lock-step runner (policies ``sweep`` and
``coarse_fine`` of :func:`hil.lockstep.run_session`, the scheduler only steering pan/tilt):
classic depth from focus by full sweeps, one clean frame per setting, and Krotkov's
coarse-to-fine search with the same sharpness measure.
"""

from __future__ import annotations

import numpy as np

from dffd.core.lens import Lens
from dffd.core.types import FrameTag
from dffd.scheduler import FocusMove
from drivers.frames import Frame
from hil.baselines import sweep_depth, tenengrad

# Sweep window half-size (px) around the target: this many equivalent radii plus a margin, so the
# whole defocused edge stays inside (largest blur radius at the range ends ≈ target radius).
SWEEP_WINDOW_RADII = 2.5
SWEEP_WINDOW_MARGIN_PX = 12
SWEEP_INITIAL_HALF_PX = 120


class SweepState:
    """Classic depth from focus: a boustrophedon sweep over the focus range, one frame a step."""

    def __init__(self, lens: Lens, n: int) -> None:
        lo, hi = lens.counts_range
        self.lens = lens
        self.n = n
        self.settings = [round(c) for c in np.linspace(lo, hi, n)]
        self.forward = True
        self.step = 0
        self.move_id = 10_000_000  # distinct from the scheduler's ids
        self.moving: int | None = None
        self.settled_at: float | None = None
        self.claim_after: float | None = None
        self.wakeup: float | None = 0.0
        self.samples: list[tuple[int, float, float, float]] = []  # counts, sharpness, t, truth
        self.half_px = SWEEP_INITIAL_HALF_PX
        self.completed = 0
        self.margin_s = 0.003
        self.exposure_s = 0.0
        self.current: int | None = None

    @property
    def frames_per_depth(self) -> int:
        """Clean frames one depth costs."""
        return self.n

    def order(self) -> list[int]:
        return self.settings if self.forward else self.settings[::-1]

    def next_move(self, now: float) -> FocusMove | None:
        if self.moving is not None or self.claim_after is not None:
            return None
        if self.wakeup is None or now < self.wakeup:
            return None
        target = self.order()[self.step]
        self.move_id += 1
        self.moving = self.move_id
        self.wakeup = None
        return FocusMove(self.move_id, target)

    def on_done(self, move_id: int, t: float) -> None:
        if move_id != self.moving:
            return
        self.moving = None
        self.current = self.order()[self.step]
        self.claim_after = t + self.margin_s

    def on_failed(self, move_id: int, t: float) -> None:
        if move_id == self.moving:
            self.moving = None
            self.wakeup = t

    def tag(self, t_mid: float, sched_tag: FrameTag) -> FrameTag:
        half = self.exposure_s / 2.0
        clean = (
            self.claim_after is not None
            and self.current is not None
            and t_mid - half >= self.claim_after
        )
        if clean:
            return FrameTag("burst", self.current, sched_tag.pan_deg, sched_tag.tilt_deg, None)
        return FrameTag("transit", None, sched_tag.pan_deg, sched_tag.tilt_deg, None)

    def on_frame(
        self,
        frame: Frame,
        tag: FrameTag,
        blob: tuple[float, float, float] | None,
        truth_z: float,
    ) -> tuple[float, float | None, float] | None:
        if tag.role != "burst" or tag.focus_counts is None:
            return None
        centre = (frame.image.shape[1] / 2.0, frame.image.shape[0] / 2.0)
        if blob is not None:
            centre = (blob[0], blob[1])
        sharp = tenengrad(frame.image, centre, self.half_px)
        self.samples.append((tag.focus_counts, sharp, frame.t, truth_z))
        # Next setting as soon as this exposure is over.
        self.claim_after = None
        self.wakeup = frame.t + self.exposure_s / 2.0 + self.margin_s
        self.step += 1
        if self.step < self.n:
            return None
        samples, self.samples = self.samples, []
        self.step = 0
        self.forward = not self.forward
        self.completed += 1
        counts = [s[0] for s in samples]
        sharpness = [s[1] for s in samples]
        z = sweep_depth(counts, sharpness, self.lens)
        peak = samples[int(np.argmax(sharpness))]
        if blob is not None:
            self.half_px = int(SWEEP_WINDOW_RADII * blob[2] + SWEEP_WINDOW_MARGIN_PX)
        return peak[2], z, peak[3]


class CoarseFineState(SweepState):
    """Krotkov-style coarse-to-fine search with the full sweep's sharpness measure: a coarse
    pass over the whole range, then a fine pass over ± one coarse step around the coarse peak;
    the depth comes from the fine pass (parabola through ln sharpness, as the full sweep)."""

    def __init__(self, lens: Lens, coarse: int, fine: int) -> None:
        super().__init__(lens, coarse)
        self.coarse = list(self.settings)
        self.fine_n = fine
        self.stage = "coarse"

    @property
    def frames_per_depth(self) -> int:
        return len(self.coarse) + self.fine_n

    def on_frame(
        self,
        frame: Frame,
        tag: FrameTag,
        blob: tuple[float, float, float] | None,
        truth_z: float,
    ) -> tuple[float, float | None, float] | None:
        if self.stage == "fine":
            done = super().on_frame(frame, tag, blob, truth_z)
            if done is not None:  # back to a coarse pass (in the direction the fine one ended)
                self.stage, self.settings, self.n = "coarse", self.coarse, len(self.coarse)
            return done
        if tag.role != "burst" or tag.focus_counts is None:
            return None
        centre = (frame.image.shape[1] / 2.0, frame.image.shape[0] / 2.0)
        if blob is not None:
            centre = (blob[0], blob[1])
        self.samples.append(
            (tag.focus_counts, tenengrad(frame.image, centre, self.half_px), frame.t, truth_z)
        )
        self.claim_after = None
        self.wakeup = frame.t + self.exposure_s / 2.0 + self.margin_s
        self.step += 1
        if self.step < self.n:
            return None
        samples, self.samples = self.samples, []
        peak = max(samples, key=lambda s: s[1])[0]
        lo, hi = self.lens.counts_range
        span = (hi - lo) / max(len(self.coarse) - 1, 1)
        a, b = max(lo, peak - span), min(hi, peak + span)
        self.settings = [round(c) for c in np.linspace(a, b, self.fine_n)]
        self.n, self.step, self.stage = self.fine_n, 0, "fine"
        self.forward = not self.forward  # back from the end the coarse pass reached
        if blob is not None:
            self.half_px = int(SWEEP_WINDOW_RADII * blob[2] + SWEEP_WINDOW_MARGIN_PX)
        return None
