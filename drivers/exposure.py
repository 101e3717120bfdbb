"""Exposure time of a network-video frame from its arrival time and its stream timestamp (pure).

A network camera does not say when it exposed a frame on *our* clock. Two estimates:

* **arrival**: ``t = arrival − latency_s``, the measured mean delay from mid-exposure to the
  frame leaving ``read()`` (``dffd calibrate --latency`` measures it). Carries the network's and
  the decoder's jitter.
* **stream**: the stream's own presentation timestamps (RTP/RTSP, files) give the spacing of the
  exposures exactly; a straight line fitted to (timestamp, arrival) over the last
  :data:`FIT_WINDOW_FRAMES` frames anchors them on the local clock (the fit averages the arrival
  jitter and follows the drift between the camera's clock and ours), and ``latency_s`` is
  subtracted as above: ``t = a·pts + b − latency_s``.

``mode = "auto"`` uses the stream timestamps only while they behave like a clock: strictly
increasing, and advancing at our clock's rate within :data:`SLOPE_TOLERANCE` over the window.
FFmpeg invents timestamps for MJPEG over HTTP (a 25 fps grid whatever the real rate), which
fails that test unless the camera really runs at 25 fps — and then the invented grid is as good
as a real one. Every decision is a pure function of the samples given; no clock is read here.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Literal

log = logging.getLogger(__name__)

TimestampMode = Literal["auto", "stream", "arrival"]

# Frames in the (pts, arrival) line fit: 2 s at 30 fps — long enough to average a few ms of
# arrival jitter down to well under a millisecond, short enough to follow clock drift.
FIT_WINDOW_FRAMES = 60
# Frames needed before stream timestamps are trusted (1 s at 30 fps; fewer were fooled by the
# burst of queued frames a stream delivers at start-up).
FIT_MIN_FRAMES = 30
# The stream clock must run at our rate within 1 %: a crystal is good to 100 ppm, while FFmpeg's
# invented 25 fps grid under a 30 fps MJPEG stream is 17 % slow.
SLOPE_TOLERANCE = 0.01
# A timestamp step this much larger than the arrival step (or backwards) means the stream
# restarted or wrapped: the window starts again.
PTS_JUMP_S = 1.0


class ExposureClock:
    """Estimates each frame's mid-exposure time on the local monotonic clock."""

    def __init__(self, mode: TimestampMode = "auto", latency_s: float = 0.0) -> None:
        self.mode: TimestampMode = mode
        self.latency_s = latency_s
        self._samples: deque[tuple[float, float]] = deque(maxlen=FIT_WINDOW_FRAMES)
        self._using_stream = False

    @property
    def using_stream(self) -> bool:
        """True while the last stamp came from the stream's timestamps."""
        return self._using_stream

    def reset(self) -> None:
        """Forget the fit (after a reconnect the stream's timestamps restart)."""
        self._samples.clear()
        self._set_using(use=False)

    def stamp(self, arrival: float, pts_s: float | None) -> float:
        """Mid-exposure time of a frame read at ``arrival`` carrying timestamp ``pts_s``."""
        if self.mode == "arrival" or pts_s is None or pts_s < 0:
            self._set_using(use=False)
            return arrival - self.latency_s
        if self._samples:
            last_pts, last_arrival = self._samples[-1]
            if pts_s <= last_pts or pts_s - last_pts > (arrival - last_arrival) + PTS_JUMP_S:
                log.debug("stream timestamp jumped %.3f -> %.3f s; refitting", last_pts, pts_s)
                self._samples.clear()
        self._samples.append((pts_s, arrival))
        fit = self._fit()
        use = fit is not None and (self.mode == "stream" or abs(fit[0] - 1.0) <= SLOPE_TOLERANCE)
        self._set_using(use=use)
        if not use or fit is None:
            return arrival - self.latency_s
        slope, intercept = fit
        return slope * pts_s + intercept - self.latency_s

    def _fit(self) -> tuple[float, float] | None:
        """Least-squares line arrival = a·pts + b over the window (None: too few frames)."""
        n = len(self._samples)
        if n < FIT_MIN_FRAMES:
            return None
        # Centre both variables: the monotonic clock is ~1e5 s, and squares of raw values lose
        # the millisecond digits in float64.
        p0, a0 = self._samples[0]
        sp = sa = spp = spa = 0.0
        for p, a in self._samples:
            dp, da = p - p0, a - a0
            sp += dp
            sa += da
            spp += dp * dp
            spa += dp * da
        var = spp - sp * sp / n
        if var <= 0.0:
            return None
        slope = (spa - sp * sa / n) / var
        intercept = a0 + (sa - slope * sp) / n - slope * p0
        return slope, intercept

    def _set_using(self, *, use: bool) -> None:
        if use != self._using_stream:
            log.info(
                "frame times from %s",
                "the stream's timestamps" if use else f"arrival − {self.latency_s * 1e3:.1f} ms",
            )
        self._using_stream = use
