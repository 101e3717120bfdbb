"""The PNG plots of a bench run: depth against truth, error over time, β̂ and R̂, and sample
cost parabolas, per session (matplotlib is imported only when plots are written)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hil.results import FloatArray, RunResult

# Parabola panels drawn from the sample bursts (spread over the run).
SAMPLE_BURSTS = 6


def write_plots(results: Sequence[RunResult], out_dir: Path) -> list[Path]:
    """Depth vs truth, error over time, β̂, R̂ and sample cost parabolas, one PNG each."""
    import matplotlib as mpl

    mpl.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    for res in results:
        stem = f"{res.case}-s{res.seed}" if len(results) > 1 else res.case
        paths += _plot_session(plt, res, out_dir, stem)
    return paths


# -- private -------------------------------------------------------------------------------------


def _plot_session(plt: Any, res: RunResult, out_dir: Path, stem: str) -> list[Path]:
    paths: list[Path] = []
    t0 = res.t_start

    def save(fig: Any, name: str) -> None:
        path = out_dir / f"{stem}-{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)

    # depth vs truth
    fig, ax = plt.subplots(figsize=(10, 5))
    truth_t, truth_z = _truth_curve(res)
    ax.plot(truth_t - t0, truth_z, "k-", lw=2, label="truth")
    for name, s in sorted(res.estimates.items()):
        t, v, _ = s.arrays()
        if name == "measured":
            ax.plot(t - t0, v, "r.", ms=3, label="z_m (measured)")
        else:
            ax.plot(t - t0, v, lw=1, label=name + (" (best)" if name == res.best else ""))
    for name, s in sorted(res.baselines.items()):
        t, v, _ = s.arrays()
        ax.plot(t - t0, v, "x", ms=3, alpha=0.6, label=f"baseline {name}")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("depth (m)")
    ax.set_title(f"{res.scenario} / {res.case} (seed {res.seed}): depth")
    ax.legend(fontsize=7, ncol=3)
    save(fig, "depth")

    # error over time
    fig, ax = plt.subplots(figsize=(10, 5))
    for name, s in sorted(res.estimates.items()):
        t, v, truth = s.arrays()
        style = "r." if name == "measured" else "-"
        ax.plot(t - t0, (v - truth) * 1e3, style, ms=3, lw=1, label=name)
    ax.axvline(res.settle_s, color="gray", ls="--", lw=1, label="settled")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("error (mm)")
    lim = _robust_ylim(res)
    if lim is not None:
        ax.set_ylim(-lim, lim)
    ax.set_title("depth error (estimate − truth)")
    ax.legend(fontsize=7, ncol=3)
    save(fig, "error")

    # bias estimate and size estimate
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    if len(res.beta):
        t, v, _ = res.beta.arrays()
        ax1.plot(t - t0, v, lw=1)
    ax1.set_ylabel("β̂ (m/s)")
    ax1.set_title("CF2 bias estimate β̂ and size estimate R̂")
    if len(res.size):
        t, v, truth = res.size.arrays()
        ax2.plot(t - t0, v * 1e3, lw=1, label="R̂")
        ax2.plot(t - t0, truth * 1e3, "k--", lw=1, label="true R")
        ax2.legend(fontsize=7)
    ax2.set_ylabel("size (mm)")
    ax2.set_xlabel("t (s)")
    save(fig, "bias-size")

    # sample cost parabolas
    sample = _sample_bursts(res)
    if sample:
        cols = 3
        rows = math.ceil(len(sample) / cols)
        fig, axes = plt.subplots(rows, cols, figsize=(10, 3.2 * rows), squeeze=False)
        for ax, b in zip(axes.flat, sample, strict=False):
            x = np.asarray(b.v0_mm)
            ax.plot(x, b.cost, "bo")
            if b.coeffs is not None:
                lo, hi = float(x.min()), float(x.max())
                pad = 0.5 * (hi - lo)
                xs = np.linspace(lo - pad, hi + pad, 100)
                a2, a1, a0 = b.coeffs
                ax.plot(xs, a2 * xs**2 + a1 * xs + a0, "b-", lw=1)
            if b.v_hat_mm is not None:
                ax.axvline(b.v_hat_mm, color="b", ls=":", lw=1, label="v̂")
            if b.truth_v_mm is not None:
                ax.axvline(b.truth_v_mm, color="k", ls="--", lw=1, label="true v")
            verdict = "ok" if b.accepted else f"rejected: {b.reason}"
            ax.set_title(f"t={b.t - t0:.1f} s z={b.truth_z_m:.2f} m {verdict}", fontsize=7)
            ax.set_xlabel("v0 (mm)", fontsize=7)
            ax.tick_params(labelsize=6)
        for ax in list(axes.flat)[len(sample) :]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=6)
        save(fig, "parabolas")
    if res.track3d is not None:
        title = f"{res.scenario} {res.case}: 3D tracker model probabilities"
        plot = res.track3d.plot(out_dir / f"{stem}-model-probabilities.png", title)
        if plot is not None:
            paths.append(plot)
    return paths


def _truth_curve(res: RunResult) -> tuple[FloatArray, FloatArray]:
    pools = [s for s in res.estimates.values() if len(s)] + [
        s for s in res.baselines.values() if len(s)
    ]
    if not pools:
        return np.zeros(0), np.zeros(0)
    longest = max(pools, key=len)
    t, _, truth = longest.arrays()
    order = np.argsort(t)
    return t[order], truth[order]


def _robust_ylim(res: RunResult) -> float | None:
    errs = []
    for s in res.estimates.values():
        t, v, truth = s.arrays()
        e = (v - truth)[(t - res.t_start) >= res.settle_s] * 1e3
        errs.append(e[np.isfinite(e)])
    if not errs or not any(e.size for e in errs):
        return None
    pooled = np.abs(np.concatenate(errs))
    return float(2.0 * np.percentile(pooled, 99)) + 1.0


def _sample_bursts(res: RunResult) -> list[Any]:
    if not res.bursts:
        return []
    rejected = [b for b in res.bursts if not b.accepted][:1]
    idx = np.linspace(0, len(res.bursts) - 1, SAMPLE_BURSTS - len(rejected)).astype(int)
    picked = [res.bursts[i] for i in sorted(set(idx.tolist()))]
    return picked + rejected
