"""SizeHistory.line: the least-squares line through the sizes of a time window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dffd.core.sizes import SizeHistory


def _history(n: int, maxlen: int = 256) -> tuple[SizeHistory, list[float], list[float]]:
    rng = np.random.default_rng(5)
    hist = SizeHistory(maxlen)
    t = 0.0
    for _ in range(n):
        t += float(rng.uniform(0.01, 0.05))
        hist.add(t, 0.01 * math.exp(0.2 * t + float(rng.normal(0, 1e-3))))
    return hist, list(hist._t), list(hist._ln)


@pytest.mark.parametrize(("lo", "hi"), [(-15, None), (-40, -10), (0, None), (-256, -250), (-3, -3)])
def test_line_is_the_least_squares_line_of_the_window(lo: int, hi: int | None) -> None:
    hist, ts, lns = _history(400)  # more frames than it keeps: the oldest are gone
    assert len(ts) == 256
    t0 = ts[lo]
    t1 = math.inf if hi is None else ts[hi]
    sel = [(t, ln) for t, ln in zip(ts, lns, strict=True) if t0 <= t <= t1]
    line = hist.line(t0, t1)
    if len(sel) < 2:
        assert line is None
        return
    assert line is not None
    t_ref, ln_ref, slope = line
    t, ln = np.array(sel).T
    fit_slope, fit_icpt = np.polyfit(t - t_ref, ln, 1)
    assert t_ref == pytest.approx(t.mean(), rel=1e-12)
    assert ln_ref == pytest.approx(fit_icpt, abs=1e-12)
    assert slope == pytest.approx(fit_slope, rel=1e-9)


def test_line_needs_two_frames_in_the_window() -> None:
    hist, ts, _ = _history(10)
    assert hist.line(ts[-1], math.inf) is None  # one frame
    assert hist.line(ts[-1] + 1.0, math.inf) is None  # none
    assert SizeHistory(8).line(0.0, math.inf) is None  # empty
