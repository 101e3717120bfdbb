"""The RTS smoother over a recorded Kalman-filter run equals the batch least-squares solution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dffd.core.filters import DepthKF, KFNoise, KFTraceEvent
from dffd.core.smoother import rts_smooth


def _record(seed: int, frames: int = 80, every: int = 6) -> tuple[list[KFTraceEvent], DepthKF]:
    """A DepthKF on a target approaching at 1 m/s from 6 m, a depth measurement every
    ``every`` frames; every step recorded, a frame marker after each frame."""
    rng = np.random.default_rng(seed)
    trace: list[KFTraceEvent] = []
    kf = DepthKF(KFNoise(sigma_rho=0.01, sigma_b=0.02), trace)
    dt, z = 1 / 30, 6.0
    for k in range(frames):
        z_next = z - dt
        if k:
            kf.predict(z_next / z, dt)  # ratio s_k/s_{k+1} = z_{k+1}/z_k
            z = z_next
        if k % every == 0:
            kf.update(z + rng.normal(0.0, 0.03), 0.03)
        trace.append(KFTraceEvent("frame", frame=k))
    return trace, kf


def _batch(trace: list[KFTraceEvent]) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the filter model's negative log posterior over all states at once: the prior
    at the reset, every transition with its Q, every measurement with its R (normal
    equations); returns the states and the diagonal blocks' z variance."""
    nodes: list[int] = []  # trace index of each node's opening event
    for i, ev in enumerate(trace):
        if ev.kind in ("reset", "predict"):
            nodes.append(i)
    n = len(nodes)
    info = np.zeros((2 * n, 2 * n))
    vec = np.zeros(2 * n)
    node = -1
    for ev in trace:
        if ev.kind == "reset":
            node = 0
            assert ev.x is not None
            assert ev.p is not None
            w = np.linalg.inv(ev.p)
            info[:2, :2] += w
            vec[:2] += w @ ev.x
        elif ev.kind == "predict":
            node += 1
            assert ev.phi is not None
            assert ev.q is not None
            a = np.zeros((2, 2 * n))  # x_node − Φ x_{node−1}
            a[:, 2 * node : 2 * node + 2] = np.eye(2)
            a[:, 2 * node - 2 : 2 * node] = -ev.phi
            info += a.T @ np.linalg.inv(ev.q) @ a
        elif ev.kind == "update":
            assert ev.y is not None
            assert ev.r is not None
            c = np.zeros(2 * n)
            c[2 * node] = 1.0
            info += np.outer(c, c) / ev.r
            vec += c * ev.y / ev.r
    x = np.linalg.solve(info, vec).reshape(n, 2)
    cov = np.linalg.inv(info)
    return x, np.array([cov[2 * k, 2 * k] for k in range(n)])


def test_rts_smoother_equals_batch_least_squares() -> None:
    trace, kf = _record(seed=5)
    # the first measurement resets the filter; the initial prior is that reset's state
    smoothed = rts_smooth(trace)
    x_batch, var_batch = _batch([ev for ev in trace if ev.kind != "frame"])
    # frame k is node k (a reset at frame 0, one prediction per later frame)
    assert sorted(smoothed) == list(range(80))
    for k, sm in smoothed.items():
        assert sm.z == pytest.approx(x_batch[k, 0], abs=1e-9)
        assert sm.x[1] == pytest.approx(x_batch[k, 1], abs=1e-9)
        assert sm.sigma_z == pytest.approx(math.sqrt(var_batch[k]), rel=1e-6)
    # at the end the smoother is the filter; before it, never less certain than the filter
    assert smoothed[79].z == pytest.approx(float(kf.x[0]), abs=1e-12)  # type: ignore[index]
    assert all(s.sigma_z <= math.sqrt(s.p_filtered[0, 0]) + 1e-12 for s in smoothed.values())


def test_smoother_restarts_at_a_reset_and_skips_frames_before_the_filter() -> None:
    trace_a, _ = _record(seed=6, frames=30)
    trace_b, _ = _record(seed=7, frames=30)
    shifted = [
        KFTraceEvent("frame", frame=e.frame + 100) if e.kind == "frame" and e.frame is not None
        else e
        for e in trace_b
    ]  # fmt: skip
    early = [KFTraceEvent("frame", frame=-1)]  # an estimate before any filter state
    both = rts_smooth(early + trace_a + shifted)
    alone_a, alone_b = rts_smooth(trace_a), rts_smooth(trace_b)
    assert -1 not in both
    assert both[5].z == pytest.approx(alone_a[5].z, abs=1e-12)
    assert both[105].z == pytest.approx(alone_b[5].z, abs=1e-12)
