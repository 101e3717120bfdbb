"""Fixed-interval Rauch–Tung–Striebel smoother over a Kalman filter's recorded steps.

``dffd replay`` records every step of the core's :class:`~dffd.core.filters.DepthKF` (resets,
predictions with their Φ and Q, updates) and a ``frame`` marker after each estimate
(:meth:`dffd.core.pipeline.Pipeline.record_kf`). Offline, the whole recording is known, so each
depth can use the measurements after it too: the RTS backward pass over the filter's own
predicted and filtered states gives, for the same linear-Gaussian model, the batch least-squares
(MAP) estimate of every state. A reset (a gap, a re-acquisition) starts an independent segment.

Backward pass, nodes ``k`` = the states after each prediction (and its update, if one followed):
``C_k = P_k|k Φ_{k+1}ᵀ P_{k+1|k}⁻¹``, ``x_k|N = x_k|k + C_k (x_{k+1}|N − x_{k+1|k})``,
``P_k|N = P_k|k + C_k (P_{k+1}|N − P_{k+1|k}) C_kᵀ``. Pure; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dffd.core.filters import KFTraceEvent

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Smoothed:
    """The smoothed state of one frame's estimate and its covariance (the model's)."""

    x: FloatArray
    p: FloatArray
    p_filtered: FloatArray  # the causal filter's covariance at the same node

    @property
    def z(self) -> float:
        """Smoothed depth."""
        return float(self.x[0])

    @property
    def sigma_z(self) -> float:
        """σ of the smoothed depth under the filter's model."""
        return float(np.sqrt(max(self.p[0, 0], 0.0)))


@dataclass(slots=True)
class _Node:
    x_prior: FloatArray
    p_prior: FloatArray
    phi: FloatArray | None  # transition from the previous node (None: a segment's first)
    x_post: FloatArray
    p_post: FloatArray


def rts_smooth(trace: Sequence[KFTraceEvent]) -> dict[int, Smoothed]:
    """Smoothed state per frame index of a recorded filter run (frames before the filter's
    first state are absent)."""
    out: dict[int, Smoothed] = {}
    nodes: list[_Node] = []
    frames: list[tuple[int, int]] = []  # (frame index, node index) of the current segment
    for ev in trace:
        if ev.kind == "reset":
            _flush(nodes, frames, out)
            nodes, frames = [], []
            assert ev.x is not None
            assert ev.p is not None
            nodes.append(_Node(ev.x, ev.p, None, ev.x, ev.p))
        elif ev.kind == "predict" and nodes:
            assert ev.x is not None
            assert ev.p is not None
            nodes.append(_Node(ev.x, ev.p, ev.phi, ev.x, ev.p))
        elif ev.kind == "update" and nodes:
            assert ev.x is not None
            assert ev.p is not None
            nodes[-1].x_post, nodes[-1].p_post = ev.x, ev.p
        elif ev.kind == "frame" and nodes and ev.frame is not None:
            frames.append((ev.frame, len(nodes) - 1))
    _flush(nodes, frames, out)
    return out


def _flush(nodes: list[_Node], frames: list[tuple[int, int]], out: dict[int, Smoothed]) -> None:
    if not nodes or not frames:
        return
    n = len(nodes)
    xs: list[FloatArray] = [nodes[-1].x_post] * n
    ps: list[FloatArray] = [nodes[-1].p_post] * n
    for k in range(n - 2, -1, -1):
        nxt = nodes[k + 1]
        assert nxt.phi is not None
        c = nodes[k].p_post @ nxt.phi.T @ np.linalg.inv(nxt.p_prior)
        xs[k] = nodes[k].x_post + c @ (xs[k + 1] - nxt.x_prior)
        ps[k] = nodes[k].p_post + c @ (ps[k + 1] - nxt.p_prior) @ c.T
    for frame, k in frames:
        out[frame] = Smoothed(xs[k], ps[k], nodes[k].p_post)
