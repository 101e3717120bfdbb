"""The target's normalised image size over the recent frames (pure, bounded).

Every frame with a contour gives the normalised size ``s = r p / F`` (``z s = R``). The pipeline
keeps the last few seconds of them to read the size at any time in between: a burst's frames are
compensated for the target's motion with ``s(t_i)/s(t_mid)``, and a burst's depth becomes a size
measurement ``R_m = z_m s(t_b)`` at its mid-time (docs/estimation.md §2).
"""

from __future__ import annotations

import math
from collections import deque

__all__ = ["SizeHistory"]


class SizeHistory:
    """``(t, ln s)`` of the last ``maxlen`` frames with a size, in time order."""

    def __init__(self, maxlen: int) -> None:
        if maxlen < 2:
            raise ValueError(f"a size history needs at least 2 frames, got {maxlen}")
        self._t: deque[float] = deque(maxlen=maxlen)
        self._ln: deque[float] = deque(maxlen=maxlen)
        # the last line() asked and its result, until the next add or clear: a tracking frame
        # that closes a burst and applies it asks for the same line twice (compensation, then
        # the transport from the burst's first frame)
        self._memo: tuple[float, float, tuple[float, float, float] | None] | None = None

    def __len__(self) -> int:
        return len(self._t)

    def clear(self) -> None:
        """Forget every size (a new target, or a gap)."""
        self._t.clear()
        self._ln.clear()
        self._memo = None

    def add(self, t: float, s: float) -> None:
        """Append the size ``s`` (> 0) seen at ``t``; a time not after the last replaces it."""
        if self._t and t <= self._t[-1]:
            self._t.pop()
            self._ln.pop()
        self._t.append(t)
        self._ln.append(math.log(s))
        self._memo = None

    def line(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        """Least-squares line through ln s of the frames in ``[t0, t1]``: ``(t_ref, ln s at
        t_ref, slope)`` with ``t_ref`` their mean time; None with fewer than two frames.

        Over the half second of a burst ``ln s`` is a straight line to well below its per-frame
        noise, and the fit averages that noise (a single frame's size is noisier).
        """
        memo = self._memo
        if memo is not None and memo[0] == t0 and memo[1] == t1:
            return memo[2]
        out = self._line(t0, t1)
        self._memo = (t0, t1, out)
        return out

    def _line(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        # The times increase strictly (add), so the frames from t0 on are a suffix: found from
        # the newest back (a burst's half second, of up to maxlen frames), then summed in order.
        ts, lns = self._t, self._ln
        first = len(ts)
        while first > 0 and ts[first - 1] >= t0:
            first -= 1
        window = [(ts[i], lns[i]) for i in range(first, len(ts)) if ts[i] <= t1]
        n = 0
        st = sl = 0.0
        for t, ln in window:
            n += 1
            st += t
            sl += ln
        if n < 2:
            return None
        tm, lm = st / n, sl / n
        stt = stl = 0.0
        for t, ln in window:
            stt += (t - tm) * (t - tm)
            stl += (t - tm) * (ln - lm)
        return tm, lm, (stl / stt if stt > 0 else 0.0)

    def ln_at(self, t: float) -> float | None:
        """ln s at ``t``, linear between the frames around it and held beyond the ends; None
        when empty."""
        ts, lns = self._t, self._ln
        n = len(ts)
        if n == 0:
            return None
        if t >= ts[-1]:
            return lns[-1]
        # the queries are recent (a burst of the last second): scan from the newest
        for k in range(n - 2, -1, -1):
            t0 = ts[k]
            if t0 <= t:
                t1 = ts[k + 1]
                w = (t - t0) / (t1 - t0)
                return (1.0 - w) * lns[k] + w * lns[k + 1]
        return lns[0]


class SizeOffset:
    """A constant offset ``δ`` of the measured image size, ``s_m = R/z + d`` (``d = δ p/F``),
    estimated from accepted bursts where the motion makes it observable.

    Each burst gives a depth ``z_m`` (σ) at the (precise) size ``s_m`` of its time:
    ``1/z_m = a s_m + c`` with ``a = 1/R`` and ``c = −d/R``. The size is the precise variable and
    the depth the noisy one, so a least-squares fit of ``1/z_m`` on ``s_m`` is unbiased (the
    reverse, ``z_m s_m`` on ``z_m``, has the depth noise on both sides and finds ``d = s`` on a
    target at rest). With the size constant (a target at rest) ``a`` and ``c`` are not separable
    and the zero-mean prior on ``d`` keeps the offset at 0.
    """

    def __init__(self, prior_sigma: float) -> None:
        if not prior_sigma > 0:
            raise ValueError(f"the offset's prior σ must be > 0, got {prior_sigma}")
        self.prior_sigma = prior_sigma  # σ of d (normalised size units)
        self.reset()

    def reset(self) -> None:
        """Forget every burst (a new target)."""
        self._info = [[0.0, 0.0], [0.0, 0.0]]  # information of (a, c)
        self._vec = [0.0, 0.0]
        self._n = 0

    @property
    def n(self) -> int:
        """Bursts used."""
        return self._n

    def add(self, z_m: float, sigma_z: float, s_m: float) -> None:
        """One accepted burst: depth ``z_m`` ± ``sigma_z`` at the measured size ``s_m``."""
        if not (z_m > 0 and sigma_z > 0 and s_m > 0):
            return
        if self._n == 0:
            # prior on c = −d a at a ≈ 1/R of the first burst
            a0 = 1.0 / (z_m * s_m)
            self._info[1][1] += 1.0 / (a0 * self.prior_sigma) ** 2
        u = 1.0 / z_m
        w = 1.0 / (sigma_z * u * u) ** 2  # σ(1/z) = σ_z / z²
        info, vec = self._info, self._vec
        info[0][0] += w * s_m * s_m
        info[0][1] += w * s_m
        info[1][0] += w * s_m
        info[1][1] += w
        vec[0] += w * s_m * u
        vec[1] += w * u
        self._n += 1

    def estimate(self) -> tuple[float, float] | None:
        """``(d, σ_d)`` in normalised size units, or None before two bursts."""
        (i00, i01), (i10, i11) = self._info
        det = i00 * i11 - i01 * i10
        if self._n < 2 or not det > 0:
            return None
        a = (i11 * self._vec[0] - i01 * self._vec[1]) / det
        c = (i00 * self._vec[1] - i10 * self._vec[0]) / det
        if not a > 0:
            return None
        var_c = i00 / det
        return -c / a, math.sqrt(var_c) / a
