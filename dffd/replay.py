"""``dffd replay RUN --out EST.jsonl [--config FILE] [--summary S.json] [--plot P.png]``.

Runs the estimation core, configured from the service config exactly as the daemon configures
it (:mod:`dffd.wiring`), on a recording (docs/design.md, recording format): one JSON line per
tracking frame, every causal estimator's depth and σ and the offline RTS smoother's
(``smoothed``, :mod:`dffd.core.smoother`); with ``truth.csv``, an error table per estimator
(bias, std, RMS, steady-state std after the settling time, p95 of |error|, in metres; 2σ
coverage and NEES of the published σ) is printed and written, and a plot of truth, ``z_m``,
every estimator and the errors can be drawn.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from dffd.cli.loading import say_if_compiling
from dffd.cli.output_path import output_problem
from dffd.config import ConfigError, load_config
from dffd.consistency import consistency_stats
from dffd.core import kernel_dispatch
from dffd.core.filters import KFTraceEvent
from dffd.core.lens import Lens, LensError
from dffd.core.pipeline import ESTIMATORS, Estimate
from dffd.core.pipeline_config import PipelineConfig
from dffd.core.smoother import Smoothed, rts_smooth
from dffd.core.tracking3d_types import Track3DEstimate
from dffd.exitcodes import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from dffd.recording import RecordingError, RecordingReader, Truth
from dffd.step import CoreStep
from dffd.wiring import pipeline_config

logger = logging.getLogger(__name__)

SCHEMA = 1
SMOOTHED = "smoothed"  # the offline RTS smoother's estimator name (replay only)


def run(args: argparse.Namespace) -> int:
    """Replay; exit 0 ok, 1 unreadable recording or an output that failed to be written, 2 bad
    arguments (an output's directory missing or not writable: checked first, as calibrate's)."""
    try:
        roi = _parse_roi(args.roi) if args.roi else None
    except ValueError as exc:
        print(f"dffd replay: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.settle is not None and args.settle < 0:
        print("dffd replay: --settle must be >= 0", file=sys.stderr)
        return EXIT_USAGE
    if args.known_size is not None and args.known_size <= 0:
        print("dffd replay: --known-size must be > 0", file=sys.stderr)
        return EXIT_USAGE
    unwritable = _output_problems(args)  # before the recording is read and the kernels load
    if unwritable:
        print("\n".join(f"dffd replay: {problem}" for problem in unwritable), file=sys.stderr)
        return EXIT_USAGE
    try:
        settings = load_config(args.config)
    except ConfigError as exc:
        print(f"dffd replay: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        reader = RecordingReader(args.run)
        lens = Lens.from_meta(reader.meta["lens"], source=f"{args.run}/meta.json lens")
    except (RecordingError, LensError) as exc:
        print(f"dffd replay: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    # The inputs are good: only now load (or, on a first run, compile) the tracker's kernels.
    say_if_compiling("replay")
    kernel_dispatch.use_compiled()
    config = pipeline_config(settings)
    if args.known_size is not None:
        config = replace(config, known_size_m=args.known_size)
    if args.best is not None:
        config = replace(config, best=args.best)
    settle = config.settle_s if args.settle is None else args.settle
    try:
        result = replay(reader, lens, config, roi=roi if roi is not None else settings.target.roi)
    except (RecordingError, OSError) as exc:
        print(f"dffd replay: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    try:
        _write_jsonl(args.out, result.lines)
    except OSError as exc:  # checked at the start; gone since (a removed or unmounted directory)
        print(f"dffd replay: cannot write --out {args.out}: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    t0 = reader.records[0].t_s if reader.records else 0.0
    print(
        f"{len(result.lines)} estimates from {len(reader)} frames -> {args.out} "
        f"({result.withheld} with depths held back before the first published one); "
        f"bursts accepted {result.accepted}, rejected {result.rejected}"
    )
    for reason, n in result.reasons.items():
        print(f"  {n} {reason}")
    if reader.truth is None:
        if args.summary is not None:
            print("dffd replay: no truth.csv in the recording; no summary written", file=sys.stderr)
    else:
        summary = summarize(
            result.lines,
            reader.truth,
            settle,
            t0,
            bursts=(result.accepted, result.rejected),
            reasons=result.reasons,
        )
        print(format_table(summary))
        if args.summary is not None:
            try:
                args.summary.write_text(json.dumps(summary, indent=2) + "\n", "utf-8")
            except OSError as exc:
                print(f"dffd replay: cannot write --summary {args.summary}: {exc}", file=sys.stderr)
                return EXIT_FAILURE
    if args.plot is not None:
        try:
            plot(result.lines, reader.truth, args.plot)
        except OSError as exc:
            print(f"dffd replay: cannot write --plot {args.plot}: {exc}", file=sys.stderr)
            return EXIT_FAILURE
    return EXIT_OK


class ReplayResult:
    """Estimate lines and burst counts of one replay.

    ``rejected`` counts every burst that gave no depth: fits the core rejected and bursts it
    dropped before a fit (fewer than three frames with a focus cost); ``reasons`` counts each
    reason (dropped ones as "dropped: …"). ``withheld`` counts the estimates whose depths the
    first-depth gate held back (their lines carry ``"published": false`` and null depths, as the
    daemon publishes them; not scored).
    """

    def __init__(self) -> None:
        self.lines: list[dict[str, Any]] = []
        self.withheld = 0
        self.accepted = 0
        self.rejected = 0
        self.reasons: dict[str, int] = {}


def replay(
    frames: Iterable[Any],
    lens: Lens,
    config: PipelineConfig,
    roi: tuple[int, int, int, int] | None = None,
) -> ReplayResult:
    """Run the core step over ``(Frame, FrameTag)`` pairs; collect JSON-ready lines."""
    core = CoreStep.build(config, lens)
    trace: list[KFTraceEvent] = []  # the KF's steps, for the offline smoother
    core.pipeline.record_kf(trace)
    if roi is not None:
        core.pipeline.acquire_roi(*roi)
    result = ReplayResult()
    for frame, tag in frames:
        step = core.step(frame, tag)
        out = step.output
        if out.measurement is not None:
            if out.measurement.accepted:
                result.accepted += 1
            else:
                result.rejected += 1
                reason = out.measurement.reason
                result.reasons[reason] = result.reasons.get(reason, 0) + 1
        if out.estimate is not None:
            result.lines.append(estimate_line(out.estimate, step.track, published=step.published))
            result.withheld += not step.published
            trace.append(KFTraceEvent("frame", frame=out.estimate.frame_index))
    add_smoothed(result.lines, rts_smooth(trace))
    for reason, n in core.pipeline.burst_rejections.items():
        result.rejected += n
        result.reasons[f"dropped: {reason}"] = n
    return result


def add_smoothed(lines: Sequence[dict[str, Any]], smoothed: dict[int, Smoothed]) -> None:
    """Put the RTS-smoothed depth into every line as estimator ``smoothed`` (``depth_m`` and
    ``sigma_m``). Its σ is the causal KF's published σ at that frame, an upper bound: the
    smoother's own model σ assumes white measurement noise, and consecutive bursts share frames
    (scaled by the model's ratio P_smoothed/P_filtered it covered 43 % of the errors at 2σ on a
    recorded approach run, NEES 5.3; bounded by the filter's, 100 %, NEES 1.2)."""
    for line in lines:
        sm = smoothed.get(line["frame"])
        depth, sigma = line["depth_m"], line["sigma_m"]
        depth[SMOOTHED] = None if sm is None else sm.z
        sigma[SMOOTHED] = None if sm is None else sigma.get("kf")


def estimate_line(
    e: Estimate, track: Track3DEstimate | None = None, *, published: bool = True
) -> dict[str, Any]:
    """One EST.jsonl object (docs/design.md §8 fields first, then the rest of the estimate).

    ``published`` False (the first-depth gate held the depths back, :mod:`dffd.first_depth`):
    every field that follows from a filter's depth is null, as in the daemon's payload; the
    burst's own ``measured`` depth stays (its ``…/measurement`` goes out as it is).

    ``sigma_m`` is the σ of every estimator (keys as ``depth_m``; null where no value),
    ``z_sigma_m`` the best's (the σ published with ``z_m``).

    The 3D tracker's fields (world frame, docs/tracking3d.md) are null on a frame without a
    track: ``track_position_m``/``track_velocity_m_s`` (the payload's ``position_m`` and
    ``velocity_m_s`` when present), ``acceleration_m_s2``, ``angular_speed_rad_s``,
    ``position_sigma_m`` and ``model_probabilities``.
    """
    line: dict[str, Any] = {
        "t_s": e.t,
        "published": published,
        "depth_m": {k: e.depth_m.get(k) for k in ESTIMATORS},
        "best": e.best,
        "r_px": e.r_px,
        "size_m": e.size_m,
        "frame": e.frame_index,
        "state": e.state,
        "z_m": e.z_m,
        "sigma_m": {k: e.sigma_by.get(k) for k in ESTIMATORS},
        "z_sigma_m": e.sigma_m,
        "measured_t_s": e.measured_t,
        "beta_m_s": e.beta_m_s,
        "rho": e.rho,
        "centroid_px": list(e.centroid_px),
        "position_m": None if e.position_m is None else list(e.position_m),
        "position_world_m": None if e.position_world_m is None else list(e.position_world_m),
        "pan_deg": e.pan_deg,
        "tilt_deg": e.tilt_deg,
        "focus_counts": e.focus_counts,
        "velocity_world_m_s": None if e.velocity_world_m_s is None else list(e.velocity_world_m_s),
        "track_position_m": None if track is None else list(track.position_m),
        "track_velocity_m_s": None if track is None else list(track.velocity_m_s),
        "acceleration_m_s2": None if track is None else list(track.acceleration_m_s2),
        "angular_speed_rad_s": None if track is None else track.angular_speed_rad_s,
        "position_sigma_m": None if track is None else list(track.position_sigma_m),
        "model_probabilities": None if track is None else dict(track.model_probabilities),
    }
    if not published:
        for key in ("depth_m", "sigma_m"):
            values: dict[str, Any] = line[key]
            line[key] = {k: v if k == "measured" else None for k, v in values.items()}
        line.update(dict.fromkeys(_DEPTH_FIELDS))
    return line


# The fields of an EST.jsonl line that follow from a filter's depth (null while held back).
_DEPTH_FIELDS = (
    "z_m", "z_sigma_m", "size_m", "beta_m_s", "position_m", "position_world_m",
    "velocity_world_m_s", "track_position_m", "track_velocity_m_s", "acceleration_m_s2",
    "angular_speed_rad_s", "position_sigma_m", "model_probabilities",
)  # fmt: skip


def error_stats(
    t: Sequence[float], err: Sequence[float], settle_until: float
) -> dict[str, float | int | None]:
    """bias, std, RMS, steady-state std (t ≥ settle_until) and p95 |error| in metres."""
    tt = np.asarray(t, dtype=np.float64)
    e = np.asarray(err, dtype=np.float64)
    ok = np.isfinite(e)
    tt, e = tt[ok], e[ok]
    if len(e) == 0:
        return {
            "n": 0,
            "bias_m": None,
            "std_m": None,
            "rms_m": None,
            "ss_std_m": None,
            "p95_abs_m": None,
        }
    ss = e[tt >= settle_until]
    return {
        "n": len(e),
        "bias_m": float(e.mean()),
        "std_m": float(e.std()),
        "rms_m": float(np.sqrt(np.mean(e * e))),
        "ss_std_m": float(ss.std()) if len(ss) > 1 else None,
        "p95_abs_m": float(np.percentile(np.abs(e), 95)),
    }


def summarize(
    lines: Sequence[dict[str, Any]],
    truth: Truth,
    settle_s: float,
    t_start: float,
    *,
    bursts: tuple[int, int],
    reasons: dict[str, int] | None = None,
) -> dict[str, Any]:
    """The SUMMARY.json object of design.md §8 (``measured`` scored at each burst's mid-time).

    The filters are scored from the first published estimate on: a line the first-depth gate
    held back has null filter depths; ``withheld_estimates`` counts those lines."""
    estimators: dict[str, Any] = {}
    for name in (*ESTIMATORS, SMOOTHED):
        ts: list[float] = []
        vals: list[float] = []
        sigmas: list[float] = []
        for line in lines:
            value = line["depth_m"].get(name)
            if value is None:
                continue
            t = (
                line["measured_t_s"]
                if name == "measured" and line.get("measured_t_s")
                else (line["t_s"])
            )
            ts.append(float(t))
            vals.append(float(value))
            sigma = (line.get("sigma_m") or {}).get(name)
            sigmas.append(math.nan if sigma is None else float(sigma))
        if not ts:
            continue
        err = np.asarray(vals) - truth.z_at(ts)
        block = error_stats(ts, err.tolist(), t_start + settle_s)
        if any(math.isfinite(x) for x in sigmas):
            block |= consistency_stats(ts, err.tolist(), sigmas, t_start + settle_s)
        estimators[name] = block
    return {
        "schema": SCHEMA,
        "settle_s": settle_s,
        "estimators": estimators,
        "withheld_estimates": sum(1 for line in lines if line.get("published") is False),
        "bursts": {"accepted": bursts[0], "rejected": bursts[1], "reasons": dict(reasons or {})},
    }


def format_table(summary: dict[str, Any]) -> str:
    """Human-readable error table (millimetres)."""
    head = (
        f"{'estimator':<10}{'n':>6}{'bias':>9}{'std':>9}{'rms':>9}{'ss std':>9}{'p95':>9}"
        f"{'2σ cov':>9}{'NEES':>9}"
    )
    rows = [head + "   (mm; 2σ coverage and NEES of the published σ)"]
    for name, st in summary["estimators"].items():

        def mm(v: float | None) -> str:
            return "-" if v is None or not math.isfinite(v) else f"{1000 * v:.1f}"

        def num(v: float | None, fmt: str) -> str:
            return "-" if v is None or not math.isfinite(v) else fmt.format(v)

        rows.append(
            f"{name:<10}{st['n']:>6}{mm(st['bias_m']):>9}{mm(st['std_m']):>9}"
            f"{mm(st['rms_m']):>9}{mm(st['ss_std_m']):>9}{mm(st['p95_abs_m']):>9}"
            f"{num(st.get('coverage_2sigma'), '{:.3f}'):>9}{num(st.get('nees'), '{:.2f}'):>9}"
        )
    b = summary["bursts"]
    rows.append(
        f"bursts accepted {b['accepted']}, rejected {b['rejected']}; "
        f"steady state after {summary['settle_s']} s"
    )
    rows.extend(f"  {n} {reason}" for reason, n in b.get("reasons", {}).items())
    return "\n".join(rows)


def plot(lines: Sequence[dict[str, Any]], truth: Truth | None, path: Path) -> None:
    """Depth of truth, z_m and every estimator, and their errors, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_z, ax_e) = plt.subplots(2, 1, sharex=True, figsize=(10, 7))
    if truth is not None:
        ax_z.plot(truth.t_s, truth.z_m, color="tab:blue", lw=1.5, label="truth")
    colours = {
        "measured": "tab:red",
        "cf1": "gold",
        "cf2": "tab:green",
        "lpv": "black",
        "kf": "tab:purple",
        SMOOTHED: "tab:cyan",
    }
    for name in (*ESTIMATORS, SMOOTHED):
        pts = [
            (ln["measured_t_s"] if name == "measured" else ln["t_s"], ln["depth_m"][name])
            for ln in lines
            if ln["depth_m"].get(name) is not None
        ]
        if not pts:
            continue
        t, z = (np.asarray(v, dtype=np.float64) for v in zip(*pts, strict=True))
        style: dict[str, Any] = (
            {"ls": "none", "marker": ".", "ms": 3} if name == "measured" else {"lw": 1.0}
        )
        ax_z.plot(t, z, color=colours[name], label=name, **style)
        if truth is not None:
            ax_e.plot(t, 1000 * (z - truth.z_at(t)), color=colours[name], label=name, **style)
    ax_z.set_ylabel("depth (m)")
    ax_z.legend(loc="best", fontsize="small")
    ax_e.set_ylabel("error (mm)")
    ax_e.set_xlabel("t (s)")
    ax_e.axhline(0.0, color="grey", lw=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _write_jsonl(path: Path, lines: Sequence[dict[str, Any]]) -> None:
    """One compact JSON object per line; NaN/inf become null (JSON has no such numbers).

    orjson: ~2 µs a line against ~34 µs for ``json.dumps`` of the same line after a pass that
    replaced the non-finite numbers — with an estimate on every frame that was 3 % of replay's
    per-frame budget at 1,000 frames/s.
    """
    option = orjson.OPT_APPEND_NEWLINE | orjson.OPT_SERIALIZE_NUMPY
    with path.open("wb") as fh:
        fh.writelines(orjson.dumps(line, option=option) for line in lines)


def _output_problems(args: argparse.Namespace) -> list[str]:
    """Why each file replay was asked to write could not be written, as calibrate's --out."""
    outputs = (
        ("--out", args.out, "estimates file", "est.jsonl"),
        ("--summary", args.summary, "summary", "summary.json"),
        ("--plot", args.plot, "plot", "plot.png"),
    )
    found = (
        output_problem(path, option=option, command="replay", what=what, example=example)
        for option, path, what, example in outputs
        if path is not None
    )
    return [problem for problem in found if problem is not None]


def _parse_roi(text: str) -> tuple[int, int, int, int]:
    parts = text.split(",")
    if len(parts) != 4:
        raise ValueError(f"--roi needs X,Y,W,H (got {text!r})")
    try:
        x, y, w, h = (int(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"--roi needs four integers X,Y,W,H (got {text!r})") from exc
    if w <= 0 or h <= 0:
        raise ValueError("--roi width and height must be > 0")
    return x, y, w, h
