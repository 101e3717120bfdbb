"""Is a published σ honest? 2σ coverage and NEES of estimates scored against a truth.

One definition for ``dffd replay``'s summary and the bench's ``report.json``: for samples with an
error ``e`` and a published standard deviation ``σ``,

* ``coverage_2sigma``: the fraction with ``|e| ≤ 2σ`` (a Gaussian error with an honest σ: 0.954;
  the goal band is [0.90, 0.98]);
* ``nees``: the mean normalised estimation error squared ``e²/σ²`` (1 for an honest σ; for a
  scalar the NEES and the NIS coincide);
* the same two in the steady state (``ss_`` prefix: samples at or after the settling time);
* ``first_abs_err_m``, ``first_sigma_m``: the first published estimate's error and σ (the
  start-up is where a filter that trusts its first, coarse measurement is most overconfident).

Samples without a finite σ > 0 are left out (``n_sigma`` counts the ones used).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

# Goal band of the 2σ coverage (issue 11: "2σ covers 90–98 % of errors").
COVERAGE_BAND = (0.90, 0.98)


def consistency_stats(
    t: Sequence[float], err: Sequence[float], sigma: Sequence[float], settle_until: float
) -> dict[str, Any]:
    """2σ coverage and NEES (whole run and steady state) of errors ``err`` against ``sigma``."""
    tt = np.asarray(t, dtype=np.float64)
    e = np.asarray(err, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    ok = np.isfinite(e) & np.isfinite(s) & (s > 0) & np.isfinite(tt)
    tt, e, s = tt[ok], e[ok], s[ok]
    out: dict[str, Any] = {"n_sigma": len(e)}
    order = np.argsort(tt, kind="stable")
    out["first_abs_err_m"] = float(abs(e[order[0]])) if len(e) else None
    out["first_sigma_m"] = float(s[order[0]]) if len(e) else None
    for prefix, sel in (("", np.ones(len(e), dtype=bool)), ("ss_", tt >= settle_until)):
        z = e[sel] / s[sel]
        out[f"{prefix}coverage_2sigma"] = float(np.mean(np.abs(z) <= 2.0)) if len(z) else None
        out[f"{prefix}nees"] = float(np.mean(z * z)) if len(z) else None
    return out


def in_band(coverage: float | None) -> bool | None:
    """Whether a 2σ coverage lies in :data:`COVERAGE_BAND` (None without a value)."""
    if coverage is None:
        return None
    return COVERAGE_BAND[0] <= coverage <= COVERAGE_BAND[1]
