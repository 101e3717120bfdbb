"""Which implementation of the tracker's kernels a pass calls: numba's, or the NumPy twins.

:func:`current` gives the compiled kernels (:mod:`dffd.core.kernels`, importing them on the first
call: loading machine code from numba's cache, or compiling it on a first start) unless
:func:`use_numpy` was called first: then the NumPy twins (:mod:`dffd.core.kernels_numpy`, same
signatures and results to rounding) run until :func:`use_compiled` swaps the compiled ones in.
``dffd run`` does that (``dffd.warmup.start_background``) so that a first start estimates within
seconds while numba compiles elsewhere. A pass reads :func:`current` once, so a swap never
splits one pass between the two implementations.
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Iterator
from typing import Literal, Protocol, cast

import numpy as np
import numpy.typing as npt

__all__ = ["KernelSet", "active", "current", "use_compiled", "use_numpy", "using"]

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]


class KernelSet(Protocol):
    """The kernels of the contour tracker's pass and of the 3D tracker's bank (both modules
    satisfy it)."""

    def normals_and_box(
        self, pts: FloatArray, normals: FloatArray, /
    ) -> tuple[float, float, float, float]:
        """Outward normals into ``normals``; the bounding box."""

    def polarity(
        self, gray: npt.NDArray[np.uint8], pts: FloatArray, normals: FloatArray, d: float, /
    ) -> float:
        """+1 when the image is brighter inside the contour than outside, else −1."""

    def resample(self, points: FloatArray, out: FloatArray, /) -> None:
        """Points uniformly spaced in arc length along a closed polygon, into ``out``."""

    def acquire_mask(
        self, gray: npt.NDArray[np.uint8], x0: int, y0: int, downscale: int,
        out: npt.NDArray[np.uint8], /,
    ) -> float:  # fmt: skip
        """Otsu's threshold of a smoothed (and downscaled) region; its mask into ``out``."""

    def sobel_pair(self, b: F32Array, gx: F32Array, gy: F32Array, /) -> None:
        """OpenCV's 3x3 Sobel of ``b`` (scale 1/8) along x into ``gx``, along y into ``gy``."""

    def sample_normals(  # noqa: PLR0917 - the kernels' positional signature
        self,
        gx: F32Array,
        gy: F32Array,
        x0: float,
        y0: float,
        pts: FloatArray,
        normals: FloatArray,
        s: int,
        bx: F32Array,
        by: F32Array,
        /,
    ) -> None:
        """Bilinear gradient samples along every normal."""

    def fit_passes(  # noqa: PLR0917 - the kernels' positional signature
        self,
        gx: F32Array,
        gy: F32Array,
        win: IntArray,
        pts_in: FloatArray,
        polarity: float,
        s: int,
        motion: int,
        relax: float,
        cfg: FloatArray,
        width: int,
        height: int,
        max_passes: int,
        refine_px: float,
        margin: int,
        state: IntArray,
        normals: FloatArray,
        bx: F32Array,
        by: F32Array,
        mag: F32Array,
        new_pts: FloatArray,
        peaks: FloatArray,
        scratch: FloatArray,
        design: FloatArray,
        out: FloatArray,
        fit: FloatArray,
        /,
    ) -> None:
        """The passes of one contour fit (resumable when a pass needs another window)."""

    def fit_pass(  # noqa: PLR0917 - the kernels' positional signature
        self,
        bx: F32Array,
        by: F32Array,
        has_window: bool,
        pts: FloatArray,
        normals: FloatArray,
        polarity: float,
        s: int,
        motion: int,
        relax: float,
        cfg: FloatArray,
        width: int,
        height: int,
        new_pts: FloatArray,
        peaks: FloatArray,
        mag: F32Array,
        scratch: FloatArray,
        design: FloatArray,
        out: FloatArray,
        /,
    ) -> None:
        """Peak search, robust fit, new contour."""

    def edge_moments(  # noqa: PLR0917 - the kernels' positional signature
        self,
        bx: F32Array,
        by: F32Array,
        normals: FloatArray,
        polarity: float,
        s: int,
        offset: FloatArray,
        inlier: FloatArray,
        sigma2_hint: float,
        k_sigma: float,
        min_half: float,
        passes: int,
        trim_fraction: float,
        var_out: FloatArray,
        mass_out: FloatArray,
        pooled: FloatArray,
        /,
    ) -> None:
        """Edge second moments along the normals and their pooled focus cost."""

    def track_predict(  # noqa: PLR0917 - the kernels' positional signature
        self,
        xs: FloatArray,
        ps: FloatArray,
        codes: IntArray,
        q: FloatArray,
        q_omega: FloatArray,
        dt: float,
        q_size: float,
        xs_out: FloatArray,
        ps_out: FloatArray,
        /,
    ) -> None:
        """Every model's prediction of the 3D tracker's bank over ``dt``."""

    def track_unit_update(  # noqa: PLR0917 - the kernels' positional signature
        self,
        xs: FloatArray,
        ps: FloatArray,
        m: FloatArray,
        sigma_m: FloatArray,
        mu: FloatArray,
        floor: float,
        xs_out: FloatArray,
        ps_out: FloatArray,
        loglik: FloatArray,
        mu_out: FloatArray,
        /,
    ) -> int:
        """Every model's update on a unit-size point and the MMAE probabilities after it; 1
        when not positive definite."""

    def track_size_update(  # noqa: PLR0917 - the kernels' positional signature
        self,
        xs: FloatArray,
        ps: FloatArray,
        size: float,
        var: float,
        xs_out: FloatArray,
        ps_out: FloatArray,
        /,
    ) -> None:
        """Every model's update on a measured size."""

    def track_combine(
        self, mu: FloatArray, xs: FloatArray, ps: FloatArray, codes: IntArray, out: FloatArray, /
    ) -> None:
        """The bank's probability-weighted estimate."""

    def focus_cost(self, peak_sq: FloatArray, trim_fraction: float, out: FloatArray, /) -> int:
        """Cost (2) of a frame's per-normal peaks into ``out`` = (g, σ_g); 0 when none."""

    def cartesian_point(  # noqa: PLR0917 - the kernels' positional signature
        self,
        u_px: float,
        v_px: float,
        pan_deg: float,
        tilt_deg: float,
        z: float,
        sigma_z_m: float,
        sigma_px: float,
        sigma_angle_deg: float,
        pixel_pitch_mm: float,
        image_distance_mm: float,
        cx: float,
        cy: float,
        world: FloatArray,
        cov: FloatArray,
        /,
    ) -> None:
        """A centroid at pan/tilt and depth as a world point and its covariance."""

    def slow_error_gammas(
        self, x: FloatArray, s: FloatArray, lags: int, gamma: FloatArray, /
    ) -> None:
        """Autocovariances (lags 0 … ``lags``) of the residuals ``(x − m)/s`` about the
        1/s²-weighted mean, into ``gamma``."""


_active: KernelSet | None = None  # None: nothing chosen yet (the compiled kernels on first use)
_compiled = False


def current() -> KernelSet:
    """The kernels to call now (imports the compiled ones if nothing was chosen yet)."""
    impl = _active
    return impl if impl is not None else use_compiled()


def use_numpy() -> None:
    """Run the NumPy twins until :func:`use_compiled` (no effect once the compiled ones run)."""
    global _active  # noqa: PLW0603 - one process-wide choice, swapped atomically
    if not _compiled:
        _active = _load("dffd.core.kernels_numpy")


def use_compiled() -> KernelSet:
    """Import the compiled kernels (load or compile them: seconds), run them from now on."""
    global _active, _compiled  # noqa: PLW0603 - one process-wide choice, swapped atomically
    impl = _load("dffd.core.kernels")
    _active = impl
    _compiled = True
    return impl


def active() -> Literal["compiled", "numpy", "none"]:
    """Which kernels :func:`current` returns now ("none": nothing imported yet)."""
    if _compiled:
        return "compiled"
    return "none" if _active is None else "numpy"


@contextlib.contextmanager
def using(impl: KernelSet) -> Iterator[None]:
    """Run ``impl`` inside the block (tests and benchmarks compare the two implementations)."""
    global _active  # noqa: PLW0603 - restored on exit
    before = _active
    _active = impl
    try:
        yield
    finally:
        _active = before


def _load(module: str) -> KernelSet:
    # imported by name: importing dffd.core.kernels is what compiles, so never at module level
    return cast(KernelSet, importlib.import_module(module))
