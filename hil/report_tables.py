"""The bench report as text: the plain table printed after a run and the Markdown tables of
``python -m hil table`` (the README's results table, issue 11's accuracy table).

They read the ``report.json`` document :mod:`hil.report` builds (or loads).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def format_table(report: dict[str, Any]) -> str:
    """A plain-text table of the report (printed after a run, pasted into hil/README.md)."""
    rows = [
        (
            "estimator", "n", "bias mm", "std mm", "rms mm", "ss std mm", "p95 mm",
            "2σ cov", "NEES", "ss 2σ cov", "ss NEES",
        )
    ]  # fmt: skip
    items = [(k, v) for k, v in report["estimators"].items()]
    items += [(f"baseline:{k}", v) for k, v in report["baselines"].items() if v]
    for name, s in items:
        rows.append(
            (
                name + (" (best)" if name == report["best"] else ""),
                str(s["n"]),
                _mm(s["bias_m"]),
                _mm(s["std_m"]),
                _mm(s["rms_m"]),
                _mm(s["ss_std_m"]),
                _mm(s["p95_abs_m"]),
                _num(s.get("coverage_2sigma"), "{:.3f}"),
                _num(s.get("nees"), "{:.2f}"),
                _num(s.get("ss_coverage_2sigma"), "{:.3f}"),
                _num(s.get("ss_nees"), "{:.2f}"),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(
            c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]
    rates = report["rates"]
    lines.append("")
    lines.append(
        "depth rate {:.2f} Hz (limit {}, ratio {}); full sweep {} Hz (dffd/sweep {}); "
        "coarse-to-fine sweep {} Hz".format(
            rates["depth_hz"],
            _num(rates["depth_limit_hz"], "{:.2f}"),
            _num(rates["depth_rate_ratio"], "{:.2f}"),
            _num(rates["full_sweep_depth_hz"], "{:.3f}"),
            _num(rates["sweep_rate_ratio"], "{:.1f}×"),
            _num(rates.get("coarse_fine_depth_hz"), "{:.3f}"),
        )
    )
    if rates.get("estimate_hz") is not None:  # reports written before the field lack it
        lines.append(
            "estimate rate {:.2f} Hz of {:.2f} frames/s (ratio {})".format(
                rates["estimate_hz"],
                rates["frame_hz"],
                _num(rates.get("estimate_rate_ratio"), "{:.2f}"),
            )
        )
    if (pt := report.get("pan_tilt")) is not None:
        lines.append(
            "pan/tilt (steady state): smear {} px mean, {} p90 (burst frames {} / {}); centre error"
            " {} px rms, {} p95; {} reversals/s; {} commands/s".format(
                _num(pt["smear_px_mean"], "{:.2f}"),
                _num(pt["smear_px_p90"], "{:.2f}"),
                _num(pt["burst_smear_px_mean"], "{:.2f}"),
                _num(pt["burst_smear_px_p90"], "{:.2f}"),
                _num(pt["centre_err_px_rms"], "{:.1f}"),
                _num(pt["centre_err_px_p95"], "{:.1f}"),
                _num(pt["reversals_per_s"], "{:.1f}"),
                _num(pt["commands_per_s"], "{:.1f}"),
            )
        )
    for name, b in (report.get("tracking_3d") or {}).items():
        if b is None:
            continue
        w = b["angular_speed"]
        lines.append(
            "3D {:<4} position {} mm rms ({} along the line of sight, {} lateral), velocity {} "
            "mm/s, acceleration {} mm/s²; ω bias {} rms {} rad/s".format(
                name,
                _num(b["position_rms_m"] * 1e3, "{:.1f}"),
                _num(_milli(b.get("position_los_rms_m")), "{:.1f}"),
                _num(_milli(b.get("position_lateral_rms_m")), "{:.1f}"),
                _num(b["velocity_rms_m_s"] * 1e3, "{:.1f}"),
                _num(b["acceleration_rms_m_s2"] * 1e3, "{:.0f}"),
                _num(w["bias_rad_s"], "{:+.4f}"),
                _num(w["rms_rad_s"], "{:.4f}"),
            )
        )
    bursts = report["bursts"]
    if "reasons" in bursts:
        why = "; ".join(f"{n} {reason}" for reason, n in bursts["reasons"].items())
        lines.append(
            f"bursts: {bursts['accepted']} accepted, {bursts['rejected']} rejected, "
            f"{bursts['dropped']} dropped"
            + (f" ({why})" if why else "")
            + (
                f"; {n} fitted with cost (2) (fallback)"
                if (n := bursts["measure_fallbacks"])
                else ""
            )
        )
    if (sp := report.get("seeds")) and sp["n"] >= 2:
        mean, sd = sp["mean"], sp["sd"]
        lines.append(
            "over {} seeds (mean ± sd): best ss rms {} ± {} mm, z_m ss std {} ± {} mm".format(
                sp["n"],
                _mm(mean["best_ss_rms_m"]),
                _mm(sd["best_ss_rms_m"]),
                _mm(mean["measured_ss_std_m"]),
                _mm(sd["measured_ss_std_m"]),
            )
        )
    lines.extend(
        "lens table fitted by dffd calibrate --sim ({} optics, seed {}): depth error rms {} "
        "mm, max {} mm over {}-{} m; v error rms {} µm{}".format(
            c["optics"],
            c["seed"],
            _mm(c["depth_err_rms_m"]),
            _mm(c["depth_err_max_abs_m"]),
            *c["score_depths_m"],
            _num(c["v_err_rms_um"], "{:.2f}"),
            _table_sigma(c),
        )
        for c in (report.get("calibration") or {}).get("tables", [])
    )
    cpu = report["cpu"]
    lines.append(
        "core CPU {} ms/frame (p95 {}); {:.0f} s of scenario in {:.1f} s wall".format(
            _num(cpu["core_ms_per_frame_mean"], "{:.2f}"),
            _num(cpu["core_ms_per_frame_p95"], "{:.2f}"),
            cpu["scenario_s"],
            cpu["wall_s"],
        )
    )
    if report.get("latency"):
        lat = report["latency"]
        lines.append(
            f"exposure→MQTT latency p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms"
        )
    for g in report.get("goals", []):
        verdict = {True: "PASS", False: "FAIL", None: "n/a"}[g["ok"]]
        lines.append(
            f"[{verdict}] {g['goal']}: {_num(g['value'], '{:.4g}')} vs {_num(g['limit'], '{:.4g}')}"
        )
    return "\n".join(lines)


def markdown_table(reports: Sequence[dict[str, Any]]) -> str:
    """One row per report: accuracy of z_m, the best estimator, CF2, LPV and the baselines (ss
    std / bias in mm), depth rates and the goals passed — the README's results table."""
    head = (
        "| scenario | mode | optics | seeds | z_m ss std | best (lpv) ss std | cf2 ss std | "
        "kf ss std | known-size ss std | ArUco ss std | full-sweep ss std | "
        "best ss rms, z_m ss std over seeds (mean ± sd) | depth Hz (limit) | full-sweep Hz | "
        "goals |"
    )
    rows = [head, "|" + "---|" * 15]

    def ss(block: dict[str, Any] | None) -> str:
        if not block or block.get("ss_std_m") is None:
            return "–"
        bias = block.get("ss_bias_m")
        b = f" ({bias * 1e3:+.0f})" if bias is not None else ""
        return f"{block['ss_std_m'] * 1e3:.1f}{b}"

    def spread(block: dict[str, Any] | None) -> str:
        if not block or block["n"] < 2:
            return "–"
        mean, sd = block["mean"], block["sd"]
        return (
            f"{_mm(mean['best_ss_rms_m'])} ± {_mm(sd['best_ss_rms_m'])}, "
            f"{_mm(mean['measured_ss_std_m'])} ± {_mm(sd['measured_ss_std_m'])}"
        )

    for r in reports:
        est, base, rates = r["estimators"], r["baselines"], r["rates"]
        goals = r.get("goals") or []
        passed = sum(1 for g in goals if g["ok"] is True)
        limit = rates.get("depth_limit_hz")
        sweep = rates.get("full_sweep_depth_hz")
        over = r.get("overrides") or {}
        mode = r["mode"] + (" +set" if any(over.get(k) for k in over) else "")
        n_seeds = len({s["seed"] for s in r.get("sessions", [])})
        rows.append(
            f"| {r['scenario']} | {mode} | {r.get('optics', '–')} | {n_seeds} | "
            f"{ss(est.get('measured'))} | {ss(est.get(r['best']))} | "
            f"{ss(est.get('cf2'))} | {ss(est.get('kf'))} | {ss(base.get('known_size'))} | "
            f"{ss(base.get('aruco'))} | {ss(base.get('full_sweep'))} | {spread(r.get('seeds'))} | "
            f"{rates['depth_hz']:.2f} ({_num(limit, '{:.2f}')}) | {_num(sweep, '{:.2f}')} | "
            f"{passed}/{len(goals)} |"
        )
    return "\n".join(rows)


def accuracy_table(reports: Sequence[dict[str, Any]]) -> str:
    """One row per report: the best estimator's steady-state RMS and raw z_m's steady-state std
    (mean ± sd over the seeds, mm), their ratio, the best estimator's 2σ coverage (all seeds
    pooled; with several seeds, the lowest and highest seed's own in brackets) and NEES (pooled),
    the estimate rate over the frame rate and the focus measure's closed-loop
    slope ± its standard error, with the sd of the true offsets it rests on (h: a slope over
    offsets that barely spread is poorly determined) — issue 11's table (``python -m hil table
    --accuracy``)."""
    head = (
        "| scenario | optics | seeds | best ss RMS (mm) | raw z_m ss std (mm) | ratio | "
        "2σ coverage | NEES | estimate rate | focus slope |"
    )
    rows = [head, "|" + "---|" * 10]
    for r in reports:
        seeds = r.get("seeds") or {}
        mean, sd = seeds.get("mean") or {}, seeds.get("sd") or {}
        best_m, raw_m = mean.get("best_ss_rms_m"), mean.get("measured_ss_std_m")

        def pm(key: str, mean: dict[str, Any] = mean, sd: dict[str, Any] = sd) -> str:
            value, spread = mean.get(key), sd.get(key)
            if value is None:
                return "–"
            return _mm(value) + (f" ± {_mm(spread)}" if spread is not None else "")

        ratio = best_m / raw_m if best_m is not None and raw_m else None
        best = r["estimators"].get(r["best"]) or {}
        coverage = _num(best.get("coverage_2sigma"), "{:.3f}")
        per_seed = [
            c
            for row in seeds.get("per_seed") or ()
            if (c := row.get("best_coverage_2sigma")) is not None
        ]
        if len(per_seed) > 1:
            coverage += f" ({min(per_seed):.2f}–{max(per_seed):.2f})"

        slope = r.get("focus_slope")
        slope_s = (
            "–"
            if not slope
            else f"{slope['slope']:.2f} ± {slope['slope_se']:.2f} "
            f"(sd {slope['true_offset_sd_h']:.2f} h)"
        )
        rows.append(
            f"| {r['scenario']} | {r.get('optics', '–')} | {seeds.get('n', 1)} | "
            f"{pm('best_ss_rms_m')} | {pm('measured_ss_std_m')} | {_num(ratio, '{:.2f}')} | "
            f"{coverage} | {_num(best.get('nees'), '{:.2f}')} | "
            f"{_num(r['rates'].get('estimate_rate_ratio'), '{:.2f}')} | {slope_s} |"
        )
    return "\n".join(rows)


# -- private -------------------------------------------------------------------------------------


def _mm(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e3:.1f}"


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None else fmt.format(x)


def _milli(x: float | None) -> float | None:
    return None if x is None else x * 1e3


def _table_sigma(c: dict[str, Any]) -> str:
    """The calibrated table's own σ and its depths swept again, when the report has them."""
    check = c.get("check")
    if not check:
        return ""
    text = "; table's own 1σ ≤ {} mm, its error {} σ rms".format(
        _num(check["sigma_depth_mm_max"], "{:.1f}"), _num(c.get("v_err_over_sigma_rms"), "{:.1f}")
    )
    if c.get("repeated_depths_m"):
        text += "; swept again at " + ", ".join(f"{z:g}" for z in c["repeated_depths_m"]) + " m"
    return text
