"""Scoring of the 3D trackers against the simulator's 3D truth: ``report.json``'s ``tracking_3d``.

Per filter (``mmae``, ``imm``, ``cv``): 3D RMS of the position, velocity and acceleration
errors (Euclidean norm, world frame) — the position's also split into its component along the
line of sight from the pan/tilt centre (where a size or depth bias lands) and the lateral rest
— and the angular speed's bias and RMS, over the frames after
the scenario's settling time; and a plot of the multiple-model filters' model probabilities
over time. Frames and signs: ``docs/tracking3d.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dffd.core.tracking3d_types import Track3DEstimate
from drivers.sim.source import FrameTruth

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Truth3D:
    """The simulator's 3D truth at one frame (world frame)."""

    position_m: Vec3
    velocity_m_s: Vec3
    acceleration_m_s2: Vec3
    angular_speed_rad_s: float


def truth_3d(truth: FrameTruth) -> Truth3D:
    """The 3D truth of one rendered frame."""
    return Truth3D(
        truth.position_world_m,
        truth.velocity_world_mps,
        truth.acceleration_world_mps2,
        truth.angular_speed_rad_s,
    )


@dataclass(slots=True)
class _Series:
    t: list[float] = field(default_factory=list)
    pos: list[Vec3] = field(default_factory=list)
    los: list[float] = field(default_factory=list)  # position error along the line of sight
    lateral: list[float] = field(default_factory=list)  # |the rest of it|
    vel: list[Vec3] = field(default_factory=list)
    acc: list[Vec3] = field(default_factory=list)
    omega: list[float] = field(default_factory=list)
    omega_true: list[float] = field(default_factory=list)
    probabilities: list[dict[str, float]] = field(default_factory=list)


class Track3DScore:
    """Collects each filter's estimate and the truth frame by frame; summarises and plots."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s
        self._series: dict[str, _Series] = {}

    def add(self, t_s: float, truth: Truth3D, estimates: Mapping[str, Track3DEstimate]) -> None:
        """One frame: ``t_s`` seconds into the session, the truth and the filters' estimates."""
        for name, est in estimates.items():
            s = self._series.setdefault(name, _Series())
            s.t.append(t_s)
            err = _sub(est.position_m, truth.position_m)
            s.pos.append(err)
            along, across = _split_los(err, truth.position_m)
            s.los.append(along)
            s.lateral.append(across)
            s.vel.append(_sub(est.velocity_m_s, truth.velocity_m_s))
            s.acc.append(_sub(est.acceleration_m_s2, truth.acceleration_m_s2))
            s.omega.append(est.angular_speed_rad_s - truth.angular_speed_rad_s)
            s.omega_true.append(truth.angular_speed_rad_s)
            s.probabilities.append(dict(est.model_probabilities))

    def block(self) -> dict[str, Any]:
        """``{filter: {n, position_rms_m, position_los_rms_m, position_lateral_rms_m,
        velocity_rms_m_s, acceleration_rms_m_s2, angular_speed: {bias_rad_s, rms_rad_s,
        truth_mean_rad_s}}}`` over the steady state (None: no frames)."""
        out: dict[str, Any] = {}
        for name, s in self._series.items():
            sel = np.asarray(s.t) >= self.settle_s
            n = int(np.count_nonzero(sel))
            if n == 0:
                out[name] = None
                continue
            omega = np.asarray(s.omega)[sel]
            out[name] = {
                "n": n,
                "position_rms_m": _rms3(s.pos, sel),
                "position_los_rms_m": _rms1(s.los, sel),
                "position_lateral_rms_m": _rms1(s.lateral, sel),
                "velocity_rms_m_s": _rms3(s.vel, sel),
                "acceleration_rms_m_s2": _rms3(s.acc, sel),
                "angular_speed": {
                    "bias_rad_s": float(np.mean(omega)),
                    "rms_rad_s": float(math.sqrt(float(np.mean(omega**2)))),
                    "truth_mean_rad_s": float(np.mean(np.asarray(s.omega_true)[sel])),
                },
            }
        return out

    def plot(self, path: Path, title: str = "") -> Path | None:
        """Model probabilities of the multiple-model filters over time (PNG); None if none."""
        multi = {
            n: s for n, s in self._series.items() if s.probabilities and len(s.probabilities[0]) > 1
        }
        if not multi:
            return None
        import matplotlib as mpl

        mpl.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(len(multi), 1, figsize=(10, 2.8 * len(multi)), squeeze=False)
        for ax, (name, s) in zip(axes[:, 0], multi.items(), strict=True):
            models = list(s.probabilities[0])
            for model in models:
                ax.plot(s.t, [p.get(model, math.nan) for p in s.probabilities], lw=1, label=model)
            ax.set_ylim(-0.02, 1.02)
            ax.set_ylabel(f"{name} μ")
            ax.axvline(self.settle_s, color="k", ls=":", lw=1)
            ax.legend(loc="upper right", fontsize=8)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("time (s)")
        axes[0, 0].set_title(title or "3D tracker model probabilities")
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        return path


def pooled_block(scores: Sequence[Track3DScore]) -> dict[str, Any]:
    """The ``tracking_3d`` block of several sessions pooled (RMS over all their frames)."""
    pooled = Track3DScore(0.0)
    for score in scores:
        for name, s in score._series.items():
            keep = [i for i, t in enumerate(s.t) if t >= score.settle_s]
            dst = pooled._series.setdefault(name, _Series())
            dst.t += [s.t[i] for i in keep]
            dst.pos += [s.pos[i] for i in keep]
            dst.los += [s.los[i] for i in keep]
            dst.lateral += [s.lateral[i] for i in keep]
            dst.vel += [s.vel[i] for i in keep]
            dst.acc += [s.acc[i] for i in keep]
            dst.omega += [s.omega[i] for i in keep]
            dst.omega_true += [s.omega_true[i] for i in keep]
            dst.probabilities += [s.probabilities[i] for i in keep]
    return pooled.block()


def _sub(a: Vec3, b: Vec3) -> Vec3:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _split_los(err: Vec3, truth: Vec3) -> tuple[float, float]:
    """``err``'s component along the line of sight to ``truth`` (from the pan/tilt centre,
    the world origin) and the norm of the rest."""
    e, p = np.asarray(err), np.asarray(truth)
    norm = float(np.linalg.norm(p))
    if not norm > 0.0:
        return 0.0, float(np.linalg.norm(e))
    along = float(e @ p) / norm
    return along, float(np.linalg.norm(e - along * p / norm))


def _rms1(values: list[float], sel: np.ndarray[Any, np.dtype[np.bool_]]) -> float:
    v = np.asarray(values, dtype=np.float64)[sel]
    return float(math.sqrt(float(np.mean(v * v))))


def _rms3(errors: list[Vec3], sel: np.ndarray[Any, np.dtype[np.bool_]]) -> float:
    e = np.asarray(errors, dtype=np.float64)[sel]
    return float(math.sqrt(float(np.mean(np.sum(e * e, axis=1)))))
