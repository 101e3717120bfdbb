"""The ``debiased_peak`` focus measure: the peak gradient's vertex, debiased by the edge moment's.

The two measures see the same frames and answer the same question with opposite strengths
(docs/estimation.md §8, §12): the edge second moment ``edge_variance`` is unbiased for any PSF
(blur variances add) but noisy (it weighs the profile's tails by x²); the peak gradient (cost
(2)) is 1.5–2× less noisy but its vertex is biased for any PSF that is not Gaussian — by an
offset and a slope across the bracket that belong to the lens, not to the target. So their
difference over many bursts measures the peak gradient's bias: ``d = x_pg − x_ev = b0 + b1 x_ev``
(vertex offsets from the bracket centre in half-brackets ``h``), fitted by recursive least
squares with forgetting (:class:`PeakBias`). Each burst's measurement is the peak gradient's
vertex less that bias (its variance plus the bias fit's): the edge moment's bias (none by
construction) at the peak gradient's noise. No constant of either optics model enters: the
prior is diffuse on ``b0`` and by default holds ``b1`` at 0 (:class:`CombineConfig`), and the
window is the noise estimates' (:mod:`dffd.core.noise`). The edge moment it is debiased against
has a wider window than the ``edge_variance`` measure's (``focus.DEBIAS_WINDOW_SIGMAS``).

Pure and deterministic; no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CombineConfig", "PeakBias", "combine_vertices"]


@dataclass(frozen=True, slots=True)
class CombineConfig:
    """Parameters of the peak-gradient bias fit."""

    # Memory in bursts (forgetting 1 − 1/W): the window of the noise estimates (noise.py), ~27 s
    # of rolling bursts; the bias is a property of the lens and the measure, it changes slowly.
    window_bursts: float = 60.0
    # Prior σ of the offset b0 (half-brackets): diffuse — §8 measured up to 0.06 h.
    prior_offset_h: float = 1.0
    # Prior σ of the slope error b1 (h per h). 0: the fit is the offset b0 alone. In closed loop
    # the offsets spread ±0.01–0.04 h, so b1 is weakly observable, and its term b1·x_ev carries
    # the edge moment's per-burst noise into every measurement: with 0.1 the debiased vertex was
    # 1.5–3× noisier than the peak gradient's on the reference optics (paper-circle seed 1,
    # simulator's table: raw z_m ss std 26.0 against 17.4 mm; with 0: 17.1; docs/estimation.md
    # §13). Chosen on the reference optics.
    prior_slope: float = 0.0


class PeakBias:
    """``d = x_pg − x_ev = b0 + b1 x_ev`` by recursive least squares with forgetting."""

    def __init__(self, config: CombineConfig | None = None) -> None:
        self.config = config if config is not None else CombineConfig()
        c = self.config
        self.theta = (0.0, 0.0)
        self._p = (c.prior_offset_h**2, 0.0, c.prior_slope**2)  # P00, P01, P11 (units of s²)
        self.residual_var: float | None = None  # variance of d about the fit (h²)
        self.count = 0

    def correction(self, x_ev: float) -> tuple[float, float]:
        """(mean, variance) of the peak gradient's bias at offset ``x_ev`` (half-brackets)."""
        b0, b1 = self.theta
        p00, p01, p11 = self._p
        s2 = self.residual_var if self.residual_var is not None else 1.0
        var = (p00 + 2.0 * p01 * x_ev + p11 * x_ev * x_ev) * s2 if self.count else p00
        return b0 + b1 * x_ev, var

    def update(self, x_ev: float, d: float, var_d: float) -> None:
        """One burst's difference ``d`` at offset ``x_ev`` (``var_d``: its stated variance,
        the prior of the residual variance before any residual is seen)."""
        if not (math.isfinite(x_ev) and math.isfinite(d) and var_d > 0):
            return
        c = self.config
        forget = 1.0 - 1.0 / c.window_bursts
        if self.count == 0:
            # P is in units of the residual variance from here on (scale-free RLS)
            self.residual_var = var_d
            self._p = tuple(p / var_d for p in self._p)  # type: ignore[assignment]
        s2 = self.residual_var if self.residual_var is not None else var_d
        b0, b1 = self.theta
        p00, p01, p11 = self._p
        ph0, ph1 = p00 + p01 * x_ev, p01 + p11 * x_ev  # P h, h = (1, x)
        s = 1.0 + ph0 + ph1 * x_ev
        k0, k1 = ph0 / s, ph1 / s
        r = d - (b0 + b1 * x_ev)
        self.theta = (b0 + k0 * r, b1 + k1 * r)
        self._p = (
            (p00 - k0 * ph0) / forget,
            (p01 - k0 * ph1) / forget,
            (p11 - k1 * ph1) / forget,
        )
        self.count += 1
        # running mean of the squared prediction residual per its predicted variance
        w = 1.0 / min(self.count + 1, c.window_bursts)
        self.residual_var = (1.0 - w) * s2 + w * r * r / s


def combine_vertices(
    x_ev: float, var_ev: float, x_pg: float, var_pg: float, bias: PeakBias
) -> tuple[float, float]:
    """(x, var) of the burst's vertex: the peak gradient's less its fitted bias (half-brackets);
    the edge moment's own while the bias fit has seen no burst. The fit then learns from this
    burst.

    Not an inverse-variance mean of the two: their errors are correlated 0.34–0.80 (the same
    image noise on the same edges; more so at long range, docs/estimation.md §12), and with that
    correlation the edge moment's optimal weight is 0–0.2 — the weights that ignore it put
    0.25–0.4 on the noisier measure (measured: raw z_m 19 against 14 mm on static targets).
    """
    b, var_b = bias.correction(x_ev)
    first = bias.count == 0
    bias.update(x_ev, x_pg - x_ev, var_ev + var_pg)
    if first or not (math.isfinite(x_pg) and var_pg > 0):
        return x_ev, var_ev
    return x_pg - b, var_pg + var_b
