"""Irregular target outlines: smooth, seeded, non-convex closed curves (issue 11, optics model 2).

A lab's target is rarely a perfect disc: a cut card, a toy, a hand-made shape. The outline here
is a star-shaped curve ``ρ(θ) = 1 + Σ_k a_k cos(k θ + φ_k)`` over harmonics 2–6 with comparable
amplitudes, scaled to a total relative amplitude :data:`IRREGULAR_AMPLITUDE`: dents and bumps
of a few pixels at 100 px, shallow enough for every boundary normal to stay on the curve (the
radius never turns back), deep enough that the outline is not convex and its ``sqrt(tr Σ)`` is
not its mean radius. The world scales it to the configured size and spins it (``rotation_dps``).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

IRREGULAR_VERTICES = 256  # polygon vertices (like the disc's): sagitta < 0.01 px at 100 px
IRREGULAR_HARMONICS = (2, 3, 4, 5, 6)
# Sum of |a_k|: 0.2 keeps ρ ≥ 0.8 (star-shaped, simple) with shallow concave dents (checked in
# tests/test_sim_optics_aberrated.py).
IRREGULAR_AMPLITUDE = 0.2


def irregular_unit_outline(seed: int, n: int = IRREGULAR_VERTICES) -> FloatArray:
    """``n`` vertices (N×2, counter-clockwise in (a, b)) of a seeded star-shaped outline, ρ ≈ 1."""
    rng = np.random.default_rng([seed, 0x0117])
    ks = np.asarray(IRREGULAR_HARMONICS, dtype=np.float64)
    amps = rng.uniform(0.5, 1.0, len(ks))
    amps *= IRREGULAR_AMPLITUDE / float(amps.sum())
    phases = rng.uniform(0.0, 2.0 * math.pi, len(ks))
    theta = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    rho = 1.0 + np.sum(amps[:, None] * np.cos(ks[:, None] * theta[None, :] + phases[:, None]), 0)
    return np.stack((rho * np.cos(theta), rho * np.sin(theta)), axis=1)
