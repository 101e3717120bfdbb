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
    "FIT_CX_IN",
    "FIT_CY_IN",
    "FIT_XMAX",
    "FIT_XMIN",
    "FIT_YMAX",
    "FIT_YMIN",
    "HUBER_K_PX",
    "IRLS_ITERATIONS",
    "MODEL_CA",
    "MODEL_CT",
    "MODEL_CV",
    "MOTION_CODE",
    "N_COMBINE",
    "N_FIT",
    "N_OUT",
    "N_SCRATCH",
    "N_STATE",
    "N_WIN",
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
    "ST_BOX",
    "ST_FAILED",
    "ST_HAS_WINDOW",
    "ST_KEPT",
    "ST_NEED_WINDOW",
    "ST_PASSES",
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


# slots of fit_passes' state vector (int64): whether it stopped for a gradient window (the box
# it needs then), the passes done, the buffer of the pass kept (-1: none yet), whether a pass
# after the first failed, and per buffer whether its pass had a window (edge samples)
ST_NEED_WINDOW, ST_PASSES, ST_KEPT, ST_FAILED = 0, 1, 2, 3
ST_BOX = 4  # 4 slots: x0, y0, x1, y1 of the window the next pass needs
ST_HAS_WINDOW = 8  # 2 slots, one per buffer
N_STATE = 10
# slots of fit_passes' float results: the box of the kept pass's new contour (NaN when it has
# none) and the centroid of the fit's input points (its first pass's)
FIT_XMIN, FIT_YMIN, FIT_XMAX, FIT_YMAX, FIT_CX_IN, FIT_CY_IN = range(6)
N_FIT = 6
# slots of the gradient window vector (int64): x0, y0, x1, y1 in the frame (x1 <= x0: none)
N_WIN = 4


class Workspace:
    """Preallocated arrays of one tracker's passes (no allocation per pass but the outputs).

    The per-pass outputs are double-buffered (first axis 2): a pass writes the buffer that does
    not hold the pass kept so far, so a failed refinement leaves the kept one intact.
    """

    __slots__ = (
        "bx", "by", "design", "fit", "mag", "n", "new_pts", "normals", "out", "peaks",
        "scratch", "state",
    )  # fmt: skip

    def __init__(self, n: int, n_steps: int) -> None:
        self.n = n
        self.normals = np.empty((2, n, 2))
        self.bx = np.zeros((2, n, n_steps), dtype=np.float32)
        self.by = np.zeros((2, n, n_steps), dtype=np.float32)
        self.mag = np.empty((n, n_steps), dtype=np.float32)
        self.new_pts = np.empty((2, n, 2))
        self.peaks = np.empty((2, n))
        self.scratch = np.empty((2, N_SCRATCH, n))
        self.design = np.empty((n, 6))
        self.out = np.empty((2, N_OUT))
        self.state = np.zeros(N_STATE, dtype=np.int64)
        self.fit = np.empty(N_FIT)


# -- the 3D tracker's kernels (dffd.core.tracking3d, dffd.core.kernels_track) ----------------
# Motion-model codes of a bank (dffd.core.motion_models): constant velocity, constant
# acceleration, coordinated turn.
MODEL_CV, MODEL_CA, MODEL_CT = 0, 1, 2
# Slots of track_combine's output: the combined state's position, velocity, acceleration
# (9), the combined turn rate, the position variances (3), the size's mean and variance.
COMBINE_STATE, COMBINE_OMEGA, COMBINE_VAR, COMBINE_SIZE, COMBINE_SIZE_VAR = 0, 9, 10, 13, 14
N_COMBINE = 15
