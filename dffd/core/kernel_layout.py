"""What the tracker's two kernel implementations share: constants, array layouts, the workspace.

The compiled kernels (:mod:`dffd.core.kernels`, numba) and their NumPy twins
(:mod:`dffd.core.kernels_numpy`, used while numba compiles) read and write the same arrays; this
module imports neither numba nor OpenCV, so importing it compiles nothing.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "COMBINE_OMEGA",
    "COMBINE_SIZE",
    "COMBINE_SIZE_VAR",
    "COMBINE_STATE",
    "COMBINE_VAR",
    "HUBER_K_PX",
    "IRLS_ITERATIONS",
    "MODEL_CA",
    "MODEL_CT",
    "MODEL_CV",
    "MOTION_CODE",
    "N_COMBINE",
    "N_OUT",
    "N_SCRATCH",
    "OUTLIER_PX",
    "OUT_CX",
    "OUT_CX_IN",
    "OUT_CY",
    "OUT_CY_IN",
    "OUT_EDGE_SIGMA2",
    "OUT_INLIER_FRACTION",
    "OUT_OK",
    "OUT_R",
    "OUT_RMS",
    "OUT_R_IN",
    "OUT_STATUS",
    "RIDGE",
    "SCRATCH_INLIER",
    "SCRATCH_OFFSET",
    "S_INTERIOR",
    "S_OFFSET",
    "S_PEAK",
    "S_RES",
    "S_TMP",
    "S_TMP2",
    "S_VALID",
    "S_W",
    "S_WIDTH2",
    "S_WNEW",
    "TINY",
    "Workspace",
]

HUBER_K_PX = 1.0  # Huber threshold on normal residuals: about 3x the sub-pixel edge noise
OUTLIER_PX = 3.0  # residuals beyond this after IRLS are clutter/occlusion, not the target edge
IRLS_ITERATIONS = 4
RIDGE = 1e-3  # keeps the tangential slide of a circle (unobservable from normals) at zero

MOTION_CODE: dict[str, int] = {"translation": 0, "similarity": 1, "affine": 2}
# slots of the kernel's scalar output vector
OUT_STATUS, OUT_OK, OUT_R, OUT_CX, OUT_CY, OUT_INLIER_FRACTION = 0, 1, 2, 3, 4, 5
OUT_RMS, OUT_EDGE_SIGMA2, OUT_CX_IN, OUT_CY_IN, OUT_R_IN = 6, 7, 8, 9, 10
N_OUT = 11
# rows of the per-normal scratch array
S_OFFSET, S_PEAK, S_VALID, S_WIDTH2, S_INTERIOR, S_W, S_WNEW, S_RES = range(8)
S_TMP, S_TMP2 = 8, 9
# what fit_pass leaves in the scratch array for edge_moments: edge offsets and inlier flags
SCRATCH_OFFSET, SCRATCH_INLIER = S_OFFSET, S_INTERIOR
N_SCRATCH = 10
TINY = 1e-6  # added before the log of |∇I|² (log-parabola), as in the reference


class Workspace:
    """Preallocated arrays of one tracker's passes (no allocation per pass but the outputs)."""

    __slots__ = ("design", "mag", "mapx", "mapy", "n", "normals", "out", "scratch")

    def __init__(self, n: int, n_steps: int) -> None:
        self.n = n
        self.normals = np.empty((n, 2))
        self.mapx = np.empty((n, n_steps), dtype=np.float32)
        self.mapy = np.empty((n, n_steps), dtype=np.float32)
        self.mag = np.empty((n, n_steps), dtype=np.float32)
        self.scratch = np.empty((N_SCRATCH, n))
        self.design = np.empty((n, 6))
        self.out = np.empty(N_OUT)


# -- the 3D tracker's kernels (dffd.core.tracking3d, dffd.core.kernels_track) ----------------
# Motion-model codes of a bank (dffd.core.motion_models): constant velocity, constant
# acceleration, coordinated turn.
MODEL_CV, MODEL_CA, MODEL_CT = 0, 1, 2
# Slots of track_combine's output: the combined state's position, velocity, acceleration
# (9), the combined turn rate, the position variances (3), the size's mean and variance.
COMBINE_STATE, COMBINE_OMEGA, COMBINE_VAR, COMBINE_SIZE, COMBINE_SIZE_VAR = 0, 9, 10, 13, 14
N_COMBINE = 15
