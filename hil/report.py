"""``report.json`` of a bench run (design.md §8 summary shape, §9 report keys): its blocks, the
goals, writing and reading it.

The per-estimator block has the shape of ``dffd replay``'s summary (n, bias_m, std_m, rms_m,
ss_std_m, p95_abs_m) so one reader serves both; the bench adds ``ss_bias_m`` and ``ss_rms_m``.
Several sessions (cases × seeds) are pooled: each contributes its own steady state (after its own
settling time). The report as text is :mod:`hil.report_tables`, its plots :mod:`hil.report_plots`.
"""

from __future__ import annotations

import datetime as dt
import itertools
import json
import logging
import math
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dffd.consistency import COVERAGE_BAND, consistency_stats, in_band
from hil.results import FloatArray, RunResult
from hil.track3d import pooled_block

logger = logging.getLogger(__name__)

REPORT_SCHEMA = 1
BASELINE_KEYS = ("known_size", "aruco", "full_sweep", "coarse_fine")
# Depth bins (m) of the diagnostics block.
DEPTH_BINS_M = (0.0, 3.0, 5.0, 7.0, 9.0, 11.0)
# git describe must answer at once; a missing git only drops the "git" field.
GIT_TIMEOUT_S = 5.0
# Estimates per frame the core must answer (docs/design.md §8: estimates at ≥ 0.9 × the frame
# rate; transit frames whose contour fails, and the frames before acquisition, give none).
ESTIMATE_RATE_RATIO_MIN = 0.9


def summary_stats(
    t: FloatArray, err: FloatArray, settle_t: float, sigma: FloatArray | None = None
) -> dict[str, Any]:
    """Error summary of design.md §8 over samples ``err`` at ``t`` (steady state: t ≥ settle_t).

    The §7 block comes from ``dffd.replay.error_stats`` (one definition for replay and bench);
    the bench adds the steady-state bias, RMS and p95; with the published ``sigma`` of every
    sample, the 2σ coverage and NEES (:func:`dffd.consistency.consistency_stats`).
    """
    from dffd.replay import error_stats

    out: dict[str, Any] = dict(error_stats(t.tolist(), err.tolist(), settle_t))
    if sigma is not None and np.isfinite(sigma).any():
        out.update(consistency_stats(t.tolist(), err.tolist(), sigma.tolist(), settle_t))
    ok = np.isfinite(err) & np.isfinite(t)
    ss = err[ok][t[ok] >= settle_t]
    out["ss_n"] = int(ss.size)
    ssm = _moments(ss)
    out["ss_bias_m"] = ssm["bias_m"]
    out["ss_rms_m"] = ssm["rms_m"]
    out["ss_p95_abs_m"] = ssm["p95_abs_m"]
    return out


def series_summary(results: Sequence[RunResult], pick: str, name: str) -> dict[str, Any] | None:
    """Pooled summary of estimate (``pick="estimates"``) or baseline series ``name``."""
    ts, errs, sigmas = [], [], []
    for res in results:
        table = res.estimates if pick == "estimates" else res.baselines
        series = table.get(name)
        if series is None or len(series) == 0:
            continue
        t, v, truth = series.arrays()
        ts.append(t - res.t_start)
        errs.append(v - truth)
        sigmas.append(series.sigmas())
    if not ts:
        return None
    # Sessions are pooled on their own clocks (t relative to each session's start).
    return summary_stats(
        np.concatenate(ts), np.concatenate(errs), results[0].settle_s, np.concatenate(sigmas)
    )


def build_report(
    results: Sequence[RunResult],
    scenario: str,
    thresholds: dict[str, float | None] | None = None,
    bench: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``report.json`` document for the sessions of one scenario run."""
    if not results:
        raise ValueError("no sessions to report")
    first = results[0]
    est_names = sorted({n for r in results for n in r.estimates})
    estimators = {n: s for n in est_names if (s := series_summary(results, "estimates", n))}
    baselines: dict[str, Any] = {}
    for key in BASELINE_KEYS:
        baselines[key] = series_summary(results, "baselines", key)
    duration = sum(r.duration_s for r in results)
    accepted = sum(r.accepted_bursts for r in results)
    depth_hz = accepted / duration if duration > 0 else 0.0
    limit = _mean([r.depth_limit_hz for r in results])
    sweep_hz = _mean([r.full_sweep_depth_hz for r in results])
    frame_hz = sum(r.frames for r in results) / duration if duration > 0 else 0.0
    estimate_hz = sum(r.estimate_frames for r in results) / duration if duration > 0 else 0.0
    rates: dict[str, Any] = {
        "depth_hz": depth_hz,
        "depth_limit_hz": limit,
        "depth_rate_ratio": depth_hz / limit if limit else None,
        "full_sweep_depth_hz": sweep_hz,
        "coarse_fine_depth_hz": _mean(
            [r.extra.get("coarse_fine_pass", {}).get("depth_hz") for r in results]
        ),
        "sweep_rate_ratio": depth_hz / sweep_hz if sweep_hz else None,
        "frame_hz": frame_hz,
        "estimate_hz": estimate_hz,
        # issue 11.5's goal: an estimate on every frame (≥ 0.9 × the frame rate)
        "estimate_rate_ratio": estimate_hz / frame_hz if frame_hz > 0 else None,
        # estimates whose depths the first-depth gate held back (dffd.first_depth): published
        # with null depths, so not scored — every score counts from the first published one
        "withheld_estimates": sum(r.withheld for r in results),
        "frames_by_role": _sum_dicts([r.frames_by_role for r in results]),
    }
    cpu_ms = np.asarray([c for r in results for c in r.core_cpu_s], dtype=np.float64) * 1e3
    wall = sum(r.wall_s for r in results)
    cpu: dict[str, Any] = {
        "core_ms_per_frame_mean": _f(cpu_ms.mean()) if cpu_ms.size else None,
        "core_ms_per_frame_p95": _f(np.percentile(cpu_ms, 95)) if cpu_ms.size else None,
        "wall_s": wall,
        "scenario_s": duration,
        "speedup_vs_real_time": duration / wall if wall > 0 else None,
    }
    lat_ms = np.asarray([x for r in results for x in r.latency_s], dtype=np.float64) * 1e3
    latency = (
        {
            "n": int(lat_ms.size),
            "p50_ms": _f(np.percentile(lat_ms, 50)),
            "p99_ms": _f(np.percentile(lat_ms, 99)),
            "max_ms": _f(lat_ms.max()),
        }
        if lat_ms.size
        else None
    )
    best = first.best
    report: dict[str, Any] = {
        "schema": REPORT_SCHEMA,
        "scenario": scenario,
        "mode": first.mode,
        "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "git": _git_describe(),
        "duration_s": duration,
        "settle_s": first.settle_s,
        "sessions": [{"case": r.case, "seed": r.seed, "duration_s": r.duration_s} for r in results],
        "best": best,
        "estimators": estimators,
        "baselines": baselines,
        "bursts": burst_counts(results),
        "focus_slope": focus_slope(results),
        "seeds": seed_spread(results),
        "rates": rates,
        "latency": latency,
        "cpu": cpu,
        "per_case": _per_case(results),
        "diagnostics": diagnostics(results),
        "pan_tilt": pan_tilt_diagnostics(results),
        "tracking_3d": tracking_3d(results),
        "notes": sorted({n for r in results for n in r.notes}),
    }
    report["goals"] = evaluate_goals(report, thresholds or {})
    if bench is not None:
        report["bench"] = bench
    return report


def burst_counts(results: Sequence[RunResult]) -> dict[str, Any]:
    """Accepted fits, and every burst that gave no depth with its reason: fits the core rejected
    (``rejected``) and bursts it dropped before a fit (``dropped``, "dropped: …" in ``reasons``);
    ``measure_fallbacks``: bursts fitted with cost (2) instead of the configured measure."""
    reasons: dict[str, int] = {}
    for r in results:
        for b in r.bursts:
            if not b.accepted:
                reasons[b.reason] = reasons.get(b.reason, 0) + 1
    drops = _sum_dicts([r.extra.get("burst_drops", {}) for r in results])
    for reason, n in drops.items():
        reasons[f"dropped: {reason}"] = n
    return {
        "accepted": sum(r.accepted_bursts for r in results),
        "rejected": sum(len(r.bursts) - r.accepted_bursts for r in results),
        "dropped": sum(drops.values()),
        "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "measure_fallbacks": sum(r.extra.get("measure_fallbacks", 0) for r in results),
    }


def focus_slope(results: Sequence[RunResult]) -> dict[str, Any] | None:
    """The focus measure's slope in closed loop: least squares of the fitted vertex's offset from
    its bracket centre on the true sharp setting's (both in half-brackets), over the accepted
    steady-state bursts; its standard error, the intercept and the spread of the true offsets
    (the slope is only as well determined as that spread allows). None without bursts."""
    x_true: list[float] = []
    x_hat: list[float] = []
    for r in results:
        t_settle = r.t_start + r.settle_s
        for b in r.bursts:
            if not b.accepted or b.v_hat_mm is None or b.truth_v_mm is None or b.t < t_settle:
                continue
            lo, hi = min(b.v0_mm), max(b.v0_mm)
            h = 0.5 * (hi - lo)
            if not h > 0:
                continue
            mid = 0.5 * (lo + hi)
            x_true.append((b.truth_v_mm - mid) / h)
            x_hat.append((b.v_hat_mm - mid) / h)
    if len(x_true) < 3:
        return None
    xt, xh = np.asarray(x_true), np.asarray(x_hat)
    spread = float(np.std(xt))
    if not spread > 0:
        return None
    slope, icpt = np.polyfit(xt, xh, 1)
    resid = xh - (slope * xt + icpt)
    se = float(np.sqrt(np.sum(resid**2) / (len(xt) - 2) / np.sum((xt - xt.mean()) ** 2)))
    return {
        "n": len(xt),
        "slope": _f(slope),
        "slope_se": se,
        "intercept_h": _f(icpt),
        "true_offset_sd_h": spread,
    }


def seed_spread(results: Sequence[RunResult]) -> dict[str, Any]:
    """Per seed (its cases pooled): the best estimator's and raw z_m's steady-state figures;
    their mean and spread (sample standard deviation, None with one seed) over the seeds."""
    best = results[0].best
    rows: list[dict[str, Any]] = []
    for seed in sorted({r.seed for r in results}):
        rs = [r for r in results if r.seed == seed]
        b = series_summary(rs, "estimates", best) or {}
        m = series_summary(rs, "estimates", "measured") or {}
        rows.append(
            {
                "seed": seed,
                "best_ss_rms_m": b.get("ss_rms_m"),
                "best_ss_std_m": b.get("ss_std_m"),
                "measured_ss_rms_m": m.get("ss_rms_m"),
                "measured_ss_std_m": m.get("ss_std_m"),
                # each seed's own coverage: with errors correlated over seconds, the pooled
                # figure of three runs moves by a few hundredths from seed to seed
                "best_coverage_2sigma": b.get("coverage_2sigma"),
            }
        )
    keys = [k for k in rows[0] if k != "seed"]
    return {
        "n": len(rows),
        "per_seed": rows,
        "mean": {k: _mean([row[k] for row in rows]) for k in keys},
        "sd": {k: _sd([row[k] for row in rows]) for k in keys},
    }


def diagnostics(results: Sequence[RunResult]) -> dict[str, Any]:
    """Error spread by true depth (steady state): where the error comes from.

    ``r_rel_err_std``: std of (tracked r − true r)/true r on track frames — the size channel's
    noise, which every fused estimate inherits as ``z · δr/r``. ``<name>_err_std_m``: std of each
    estimator's error in the same depth bin; ``n``: track frames in the bin.
    """
    edges = DEPTH_BINS_M
    rows: dict[str, dict[str, Any]] = {}
    for lo, hi in itertools.pairwise(edges):
        key = f"{lo:g}-{hi:g}m"
        row: dict[str, Any] = {}
        rel, n = [], 0
        for res in results:
            t, r, r_true = res.r_px.arrays()
            _, z, _ = res.truth_depth.arrays()
            sel = (z >= lo) & (z < hi) & ((t - res.t_start) >= res.settle_s)
            n += int(sel.sum())
            rel.append(((r - r_true) / r_true)[sel])
        rr = np.concatenate(rel) if rel else np.zeros(0)
        rr = rr[np.isfinite(rr)]
        row["n"] = n
        row["r_rel_bias"] = _f(rr.mean()) if rr.size else None
        row["r_rel_err_std"] = _f(rr.std()) if rr.size else None
        for name in sorted({k for r in results for k in r.estimates}):
            errs = []
            for res in results:
                s = res.estimates.get(name)
                if s is None or not len(s):
                    continue
                t, v, truth = s.arrays()
                sel = (truth >= lo) & (truth < hi) & ((t - res.t_start) >= res.settle_s)
                errs.append((v - truth)[sel])
            e = np.concatenate(errs) if errs else np.zeros(0)
            e = e[np.isfinite(e)]
            row[f"{name}_err_std_m"] = _f(e.std()) if e.size > 1 else None
        if n or any(v is not None for k, v in row.items() if k.endswith("_m")):
            rows[key] = row
    return {"by_true_depth": rows}


def tracking_3d(results: Sequence[RunResult]) -> dict[str, Any] | None:
    """The ``tracking_3d`` block: each 3D tracker against the 3D truth, sessions pooled.

    Per filter (mmae, imm, cv): 3D position/velocity/acceleration RMS and the angular speed's
    bias and RMS after settling (hil/track3d.py). None when no session scored the trackers (the
    real-time and hardware runners do not yet).
    """
    scores = [r.track3d for r in results if r.track3d is not None]
    block = pooled_block(scores) if scores else {}
    return block or None


def pan_tilt_diagnostics(results: Sequence[RunResult]) -> dict[str, Any] | None:
    """Head behaviour in steady state (lock-step runs; truth from the simulator).

    ``smear_px``: the target's image motion during the exposure on track/burst frames (what
    blurs the edges the estimator measures), mean and p90; ``burst_smear_px`` the same on burst
    frames; ``centre_err_px``: distance of the target's centroid from the image centre, RMS and
    p95; ``reversals_per_s``: sign changes of the head's frame-to-frame pan or tilt velocity
    (hunting); ``commands_per_s``: pan/tilt commands (not inquiries) per second of the whole run.
    """
    smear: list[float] = []
    burst: list[float] = []
    centre: list[float] = []
    reversals = 0
    span = 0.0
    commands = 0
    duration = 0.0
    for res in results:
        rows = [r for r in res.extra.get("pan_tilt_samples", []) if r[0] >= res.settle_s]
        if len(rows) < 3:
            continue
        smear += [r[2] for r in rows if r[1] != "transit"]
        burst += [r[2] for r in rows if r[1] == "burst"]
        centre += [r[3] for r in rows]
        t = np.asarray([r[0] for r in rows])
        for col in (4, 5):
            v = np.diff(np.asarray([r[col] for r in rows]))
            s = np.sign(v[np.abs(v) > 1e-9])
            reversals += int(np.count_nonzero(s[1:] != s[:-1]))
        span += float(t[-1] - t[0])
        commands += int(res.extra.get("scheduler", {}).get("pan_tilt_commands", 0))
        duration += res.duration_s
    if not smear or span <= 0:
        return None
    sm, bu, ce = np.asarray(smear), np.asarray(burst), np.asarray(centre)
    return {
        "smear_px_mean": _f(sm.mean()),
        "smear_px_p90": _f(np.percentile(sm, 90)),
        "burst_smear_px_mean": _f(bu.mean()) if bu.size else None,
        "burst_smear_px_p90": _f(np.percentile(bu, 90)) if bu.size else None,
        "centre_err_px_rms": _f(np.sqrt(np.mean(ce**2))),
        "centre_err_px_p95": _f(np.percentile(ce, 95)),
        "reversals_per_s": reversals / span,
        "commands_per_s": commands / duration if duration > 0 else None,
    }


def evaluate_goals(report: dict[str, Any], thresholds: dict[str, float | None]) -> list[Any]:
    """The issue's accuracy and rate goals, each with its value, limit and verdict."""
    goals: list[dict[str, Any]] = []
    est = report["estimators"]
    best = est.get(report["best"])
    measured = est.get("measured")

    def add(name: str, value: float | None, limit: float | None, ok: bool | None) -> None:
        goals.append({"goal": name, "value": value, "limit": limit, "ok": ok})

    if best is not None and (lim := thresholds.get("ss_std_max_m")) is not None:
        v = best["ss_std_m"]
        add(f"{report['best']} ss_std_m < limit", v, lim, _lt(v, lim))
    if best is not None and measured is not None:
        lim = thresholds.get("ss_std_vs_measured_max")
        if lim is not None:
            ratio = _ratio(best["ss_std_m"], measured["ss_std_m"])
            add(f"{report['best']} ss_std / measured ss_std ≤ limit", ratio, lim, _le(ratio, lim))
    if "lpv" in est and "cf2" in est:
        a, b = est["lpv"]["ss_std_m"], est["cf2"]["ss_std_m"]
        add("lpv ss_std_m ≤ cf2 ss_std_m", a, b, _le(a, b))
    if best is not None and (cov := best.get("coverage_2sigma")) is not None:
        # the published σ (the best estimator's) against its errors, whole run
        add(f"{report['best']} 2σ coverage in {list(COVERAGE_BAND)}", cov, None, in_band(cov))
    rates = report["rates"]
    if (lim := thresholds.get("sweep_rate_ratio_min")) is not None:
        r = rates.get("sweep_rate_ratio")
        add("depth_hz / full_sweep_depth_hz ≥ limit", r, lim, None if r is None else r >= lim)
    r = rates.get("estimate_rate_ratio")
    if r is not None:
        lim = ESTIMATE_RATE_RATIO_MIN
        add("estimate_hz / frame_hz ≥ limit", r, lim, r >= lim)
    sweep = report["baselines"].get("full_sweep")
    if sweep is not None and measured is not None:
        # "at no worse accuracy": raw z_m against the sweep's depths, both steady state.
        a, b = measured["ss_rms_m"], sweep["ss_rms_m"]
        add("measured ss_rms_m ≤ full_sweep ss_rms_m", a, b, _le(a, b))
    return goals


def write_report(report: dict[str, Any], out_dir: Path) -> Path:
    """Write ``report.json`` into ``out_dir``; return its path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "report.json"
    path.write_text(json.dumps(_clean(report), indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path


def load_report(path: Path) -> dict[str, Any]:
    """Read a ``report.json`` (or a directory holding one)."""
    if path.is_dir():
        path = path / "report.json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(
            f"cannot read report {path}: {exc}; run `python -m hil run` first"
        ) from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"report {path} is not valid JSON: {exc}") from exc
    if not isinstance(data, dict) or "estimators" not in data:
        raise ValueError(f"{path} is not a bench report (no 'estimators' block)")
    return data


# -- private -------------------------------------------------------------------------------------


def _per_case(results: Sequence[RunResult]) -> dict[str, Any]:
    cases = sorted({r.case for r in results})
    if len(cases) < 2:
        return {}
    out: dict[str, Any] = {}
    for case in cases:
        rs = [r for r in results if r.case == case]
        names = sorted({n for r in rs for n in r.estimates})
        out[case] = {
            "estimators": {n: s for n in names if (s := series_summary(rs, "estimates", n))},
            "baselines": {k: series_summary(rs, "baselines", k) for k in BASELINE_KEYS},
            "depth_hz": sum(r.accepted_bursts for r in rs) / sum(r.duration_s for r in rs),
        }
    return out


def _moments(e: FloatArray) -> dict[str, float | None]:
    if e.size == 0:
        return {"bias_m": None, "std_m": None, "rms_m": None, "p95_abs_m": None}
    return {
        "bias_m": _f(e.mean()),
        "std_m": _f(e.std()),
        "rms_m": _f(np.sqrt(np.mean(e**2))),
        "p95_abs_m": _f(np.percentile(np.abs(e), 95)),
    }


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else None


def _sd(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return _f(np.std(vals, ddof=1)) if len(vals) >= 2 else None


def _sum_dicts(ds: Sequence[dict[str, int]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for d in ds:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def _f(x: Any) -> float:
    return float(x)


def _lt(a: float | None, b: float | None) -> bool | None:
    return None if a is None or b is None else a < b


def _le(a: float | None, b: float | None) -> bool | None:
    return None if a is None or b is None else a <= b


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def _clean(obj: Any) -> Any:
    """Replace NaN/inf by None so the JSON is strict."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.floating | np.integer):
        return _clean(obj.item())
    return obj


def _git_describe() -> str | None:
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty"],  # noqa: S607 - git from PATH on purpose
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
            cwd=Path(__file__).parent,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None
