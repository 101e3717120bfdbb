"""Target acquisition and active-contour boundary tracking (DESIGN §2, issue 4).

The contour is a closed polygon of ``Nl`` points, uniformly spaced in arc length, with outward
normals. Each frame, the image gradient is computed on the target's neighbourhood only; along every
normal the maximum of ``||∇I||²`` of the target's polarity is located with sub-pixel precision; the
normal displacements are fitted robustly (IRLS, Huber weights, gross outliers dropped) with a
shape-space motion (translation, similarity or affine about the centroid); the fitted motion is
applied to the predicted contour, which is finally relaxed a little toward the measured edges and
resampled. The same per-normal maxima feed the focus cost (2).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, TypeVar, cast

import cv2
import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Motion = Literal["translation", "similarity", "affine"]
_F = TypeVar("_F", bound=Callable[..., Any])

logger = logging.getLogger(__name__)

HUBER_K_PX = 1.0  # Huber threshold on normal residuals: about 3x the sub-pixel edge noise
OUTLIER_PX = 3.0  # residuals beyond this after IRLS are clutter/occlusion, not the target edge
IRLS_ITERATIONS = 4
# Extra border of the per-frame gradient window: the passes after the first move the contour by a
# pixel or two (measured on the reference simulator), so they reuse the first pass's gradient.
GRADIENT_SLACK_PX = 4
RIDGE = 1e-3  # keeps the tangential slide of a circle (unobservable from normals) at zero


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    """Active-contour parameters; defaults suit 640×480 targets of 20–150 px radius."""

    n_normals: int = 64  # Nl in (2)
    search_px: int = 12  # half-length of each normal line (motion + blur of a burst)
    presmooth_sigma_px: float = 1.0  # smoothing before ∇: adds to σ0, (2) stays a parabola
    min_rel_peak: float = 0.2  # a normal's peak must reach this fraction of the median peak
    min_abs_grad: float = 3.0  # gray levels / px: below this a peak is noise
    min_inlier_fraction: float = 0.5  # fewer inliers than this: the frame does not see the target
    lost_after_frames: int = 3  # consecutive bad frames before the target is declared lost
    # per frame, fraction of the non-rigid residual adopted; 0 keeps the acquired shape (r then
    # carries no memory of past noise, which the filters prefer); > 0 follows deforming shapes
    relax: float = 0.0
    min_radius_px: float = 6.0
    max_radius_px: float = 220.0
    trim_fraction: float = 0.1  # trimmed mean of per-normal peaks for the focus cost
    # Gauss-Newton passes per frame: search again along the normals of the updated contour while
    # the last pass moved it by more than ``refine_px``. One pass is biased when the prediction is
    # off by t px: along a normal the edge of a circle of radius a lies at n·t − (|t|² −
    # (n·t)²)/(2a), so r shrinks by ~|t|²/(4a) — 1.6 px (7 %) for a 12 px pan/tilt jump at 23 px
    # (measured on the reference simulator); after a second pass the residual t is sub-pixel.
    max_passes: int = 3
    curvature_correction: bool = True  # add σ²/(2r) to r (see _step)
    refine_px: float = 0.3


@dataclass(frozen=True, slots=True)
class BoundaryObservation:
    """What one frame tells about the target boundary."""

    points: FloatArray  # (Nl, 2) contour after the update, uniform in arc length, px
    centroid: tuple[float, float]  # px, image coordinates
    r_px: float  # sqrt(tr Σ) of the boundary, corrected for the edge-curvature shift (below)
    peak_sq: FloatArray  # (Nl,) max ||∇I||² per normal (NaN where no valid edge)
    inlier_fraction: float
    residual_px: float  # RMS normal residual of inliers after the fit
    ok: bool  # enough inliers and a plausible shape
    edge_sigma_px: float = math.nan  # Gaussian width of the edge (median over inlier normals)


class ContourTracker:
    """Tracks one closed boundary frame to frame; pure given its inputs (no I/O, no clock)."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._points: FloatArray | None = None
        self._velocity = np.zeros(2)  # centroid px / s
        self._t: float | None = None
        self._polarity = 1.0  # +1: intensity drops outward (bright target)
        self._bad_frames = 0
        self._ws: _Workspace | None = None
        self._cfg_vec = np.array(
            [
                config.min_rel_peak,
                config.min_abs_grad,
                config.min_inlier_fraction,
                config.min_radius_px,
                config.max_radius_px,
                1.0 if config.curvature_correction else 0.0,
            ]
        )

    @property
    def active(self) -> bool:
        """True while a contour is held."""
        return self._points is not None

    @property
    def points(self) -> FloatArray | None:
        """Current contour (copy) or None."""
        return None if self._points is None else self._points.copy()

    @property
    def bad_frames(self) -> int:
        """Consecutive frames without enough inliers."""
        return self._bad_frames

    def reset(self) -> None:
        """Drop the contour."""
        self._points = None
        self._velocity = np.zeros(2)
        self._t = None
        self._bad_frames = 0

    def start(self, gray: npt.NDArray[np.uint8], points: FloatArray, t: float) -> bool:
        """Take ``points`` (any closed polygon) as the target boundary and refine it on ``gray``."""
        pts = resample_closed(np.asarray(points, dtype=np.float64), self.config.n_normals)
        self._points = pts
        self._velocity = np.zeros(2)
        self._t = t
        self._bad_frames = 0
        self._polarity = self._estimate_polarity(gray, pts)
        obs: BoundaryObservation | None = None
        grad = _GradientCache(gray, self.config.presmooth_sigma_px)
        for _ in range(6):
            obs, _, _ = self._step(grad, self._points, "affine", relax=0.5)
            if not obs.ok:
                self.reset()
                return False
            self._points = obs.points
        return obs is not None and obs.ok

    def update(self, gray: npt.NDArray[np.uint8], t: float, motion: Motion) -> BoundaryObservation:
        """Predict to time ``t``, measure on ``gray`` and update; raises if not active."""
        if self._points is None or self._t is None:
            raise RuntimeError("ContourTracker.update called without an active contour")
        dt = max(t - self._t, 0.0)
        predicted = self._points + self._velocity * dt
        relax = self.config.relax if motion != "translation" else 0.0
        grad = _GradientCache(gray, self.config.presmooth_sigma_px)
        obs, c_in, r_in = self._step(grad, predicted, motion, relax)
        for _ in range(self.config.max_passes - 1):
            if not obs.ok:
                break
            moved = math.hypot(obs.centroid[0] - c_in[0], obs.centroid[1] - c_in[1])
            if moved + abs(obs.r_px - r_in) <= self.config.refine_px:
                break
            again, c_in, r_in = self._step(grad, obs.points, motion, relax)
            if not again.ok:
                break
            obs = again
        if obs.ok:
            if dt > 0:
                old = self._points.mean(axis=0)
                new = np.asarray(obs.centroid)
                # alpha-filtered velocity: a single noisy frame must not throw the prediction
                self._velocity = 0.6 * self._velocity + 0.4 * (new - old) / dt
            self._points = obs.points
            self._bad_frames = 0
        else:
            self._points = predicted
            self._bad_frames += 1
        self._t = t
        return obs

    @property
    def lost(self) -> bool:
        """True once too many consecutive frames failed."""
        return self._bad_frames >= self.config.lost_after_frames

    # -- one measurement + fit on one image -------------------------------------------------
    def _step(
        self, grad: _GradientCache, pts: FloatArray, motion: Motion, relax: float
    ) -> tuple[BoundaryObservation, tuple[float, float], float]:
        """One pass: (observation, centroid of ``pts``, radius_of(``pts``)).

        The per-normal search and the robust fit run in the compiled kernels below; their
        NumPy reference is kept in tests/test_core_contour.py, which checks them against it.
        """
        cfg = self.config
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        n = len(pts)
        ws = self._workspace(n)
        xmin, ymin, xmax, ymax = _kernel_normals(pts, ws.normals)
        s = cfg.search_px
        window = grad.window(xmin, ymin, xmax, ymax, s + 4)
        if window is None:
            has_window = False
            bx = by = ws.mapx  # not read by the kernel
        else:
            gx, gy, x0, y0 = window
            _kernel_maps(pts, ws.normals, s, float(x0), float(y0), ws.mapx, ws.mapy)
            bx = np.asarray(cv2.remap(gx, ws.mapx, ws.mapy, cv2.INTER_LINEAR), dtype=np.float32)
            by = np.asarray(cv2.remap(gy, ws.mapx, ws.mapy, cv2.INTER_LINEAR), dtype=np.float32)
            has_window = True
        new_pts = np.empty((n, 2))
        peaks = np.empty(n)
        out = ws.out
        _kernel_fit(
            bx, by, has_window, pts, ws.normals, self._polarity, s, _MOTION_CODE[motion],
            relax, self._cfg_vec, grad.shape[1], grad.shape[0], new_pts, peaks, ws.mag,
            ws.scratch, ws.design, out,
        )  # fmt: skip
        centroid_in = (float(out[_O_CX_IN]), float(out[_O_CY_IN]))
        r_in = float(out[_O_R_IN])
        inlier_fraction = float(out[_O_INLIER_FRACTION])
        if out[_O_STATUS] != 0:
            return _bad(pts, centroid_in, r_in, n, inlier_fraction), centroid_in, r_in
        edge_sigma2 = float(out[_O_EDGE_SIGMA2])
        obs = BoundaryObservation(
            points=new_pts,
            centroid=(float(out[_O_CX]), float(out[_O_CY])),
            r_px=float(out[_O_R]),
            peak_sq=peaks,
            inlier_fraction=inlier_fraction,
            residual_px=float(out[_O_RMS]),
            ok=bool(out[_O_OK] != 0),
            edge_sigma_px=math.sqrt(edge_sigma2) if math.isfinite(edge_sigma2) else math.nan,
        )
        return obs, centroid_in, r_in

    def _workspace(self, n: int) -> _Workspace:
        ws = self._ws
        if ws is None or ws.n != n:
            ws = self._ws = _Workspace(n, 2 * self.config.search_px + 1)
        return ws

    def _estimate_polarity(self, gray: npt.NDArray[np.uint8], pts: FloatArray) -> float:
        normals = outward_normals(pts)
        inside = _sample(gray, pts - 3.0 * normals)
        outside = _sample(gray, pts + 3.0 * normals)
        return 1.0 if float(np.median(inside - outside)) >= 0 else -1.0


# -- acquisition ----------------------------------------------------------------------------
def find_target(
    gray: npt.NDArray[np.uint8],
    roi: tuple[int, int, int, int] | None = None,
    min_radius_px: float = 6.0,
) -> FloatArray | None:
    """The most salient closed high-contrast blob in ``roi`` (x, y, w, h) or the whole image.

    Otsu threshold of the smoothed region (both polarities), external contours that do not touch
    the region border; score = area x circularity / (1 + distance to the region centre / size).
    Returns the boundary polygon in image coordinates, or None.
    """
    h, w = gray.shape[:2]
    if roi is None:
        x, y, rw, rh = 0, 0, w, h
    else:
        x, y, rw, rh = roi
        x, y = max(int(x), 0), max(int(y), 0)
        rw, rh = min(int(rw), w - x), min(int(rh), h - y)
    if rw < 8 or rh < 8:
        return None
    patch = cv2.GaussianBlur(gray[y : y + rh, x : x + rw], (5, 5), 1.0)
    _, binary = cv2.threshold(patch, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    centre = np.array([rw / 2.0, rh / 2.0])
    best: tuple[float, npt.NDArray[np.int32]] | None = None
    for mask in (binary, cv2.bitwise_not(binary)):
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for raw in contours:
            cnt = np.asarray(raw, dtype=np.int32)
            area = float(cv2.contourArea(cnt))
            if area < math.pi * min_radius_px**2 or area > 0.8 * rw * rh:
                continue
            bx, by, bw, bh = cv2.boundingRect(cnt)
            if bx <= 0 or by <= 0 or bx + bw >= rw or by + bh >= rh:
                continue  # touches the region border: background or a cut-off object
            perimeter = float(cv2.arcLength(cnt, closed=True))
            circularity = 4 * math.pi * area / max(perimeter**2, 1e-9)
            m = cnt.reshape(-1, 2).mean(axis=0)
            dist = float(np.hypot(*(m - centre)))
            score = area * circularity / (1.0 + dist / math.sqrt(area))
            if best is None or score > best[0]:
                best = (score, cnt)
    if best is None:
        return None
    poly = best[1].reshape(-1, 2).astype(np.float64) + np.array([x, y], dtype=np.float64)
    return poly


# -- geometry helpers (public: the pipeline and tests use them) -----------------------------
def gradient(
    patch: npt.NDArray[np.uint8], presmooth_sigma_px: float
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Image gradient (gray levels / px) of a gray or BGR patch after Gaussian smoothing."""
    gray = cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY) if patch.ndim == 3 else patch
    img = np.asarray(gray, dtype=np.float32)
    if presmooth_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), presmooth_sigma_px), dtype=np.float32)
    # Sobel 3x3 sums 8x the per-pixel derivative
    gx = np.asarray(cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), dtype=np.float32)
    gy = np.asarray(cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), dtype=np.float32)
    return gx, gy


def resample_closed(points: FloatArray, n: int) -> FloatArray:
    """``n`` points uniformly spaced in arc length along the closed polygon ``points``."""
    closed = np.vstack([points, points[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = cum[-1]
    if total <= 0:
        return np.repeat(points[:1], n, axis=0)
    s = np.arange(n) * (total / n)
    x = np.interp(s, cum, closed[:, 0])
    y = np.interp(s, cum, closed[:, 1])
    return np.column_stack([x, y])


def outward_normals(points: FloatArray) -> FloatArray:
    """Unit normals pointing away from the polygon's interior (either orientation)."""
    nxt, prv = _neighbours(len(points))
    tangent = points[nxt] - points[prv]
    normals = np.empty_like(tangent)
    normals[:, 0] = tangent[:, 1]
    normals[:, 1] = -tangent[:, 0]
    norm = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    normals /= np.maximum(norm, 1e-12)[:, None]
    # signed area > 0 means counter-clockwise in image coordinates (y down): flip to outward
    x, y = points[:, 0], points[:, 1]
    area = 0.5 * float(x @ y[nxt] - x[nxt] @ y)
    return normals if area < 0 else -normals


def radius_of(points: FloatArray) -> float:
    """Rotation-invariant image size r = sqrt(tr Σ) of boundary points (DESIGN §2)."""
    d = points - points.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _bad(
    pts: FloatArray, centroid: tuple[float, float], r_px: float, n: int, inlier_fraction: float
) -> BoundaryObservation:
    return BoundaryObservation(
        points=pts,
        centroid=centroid,
        r_px=r_px,
        peak_sq=np.full(n, np.nan),
        inlier_fraction=inlier_fraction,
        residual_px=math.nan,
        ok=False,
    )


def _sample(gray: npt.NDArray[np.uint8], pts: FloatArray) -> FloatArray:
    img = gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    mx = pts[:, 0].astype(np.float32).reshape(1, -1)
    my = pts[:, 1].astype(np.float32).reshape(1, -1)
    out = cv2.remap(
        img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return np.asarray(out, dtype=np.float64).ravel()


class _GradientCache:
    """The pre-smoothed gradient of one frame around the target, computed once per frame.

    The passes of one update search nearly the same neighbourhood: the window is grown by
    ``GRADIENT_SLACK_PX`` so that the following passes (the contour moves by a pixel or two)
    reuse it; a pass that leaves it recomputes a window around its own contour.
    """

    __slots__ = ("_box", "_gray", "_gx", "_gy", "_sigma", "shape")

    def __init__(self, gray: npt.NDArray[np.uint8], presmooth_sigma_px: float) -> None:
        self._gray = gray
        self._sigma = presmooth_sigma_px
        self._box: tuple[int, int, int, int] | None = None
        self._gx: npt.NDArray[np.float32] | None = None
        self._gy: npt.NDArray[np.float32] | None = None
        self.shape: tuple[int, int] = (int(gray.shape[0]), int(gray.shape[1]))

    def window(
        self, xmin: float, ymin: float, xmax: float, ymax: float, margin: int
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], int, int] | None:
        """(gx, gy, x0, y0) of a window holding the box of the points ± ``margin``, or None."""
        h, w = self.shape
        x0 = max(math.floor(xmin) - margin, 0)
        y0 = max(math.floor(ymin) - margin, 0)
        x1 = min(math.ceil(xmax) + margin + 1, w)
        y1 = min(math.ceil(ymax) + margin + 1, h)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return None
        box = self._box
        if box is None or x0 < box[0] or y0 < box[1] or x1 > box[2] or y1 > box[3]:
            slack = GRADIENT_SLACK_PX
            box = (max(x0 - slack, 0), max(y0 - slack, 0), min(x1 + slack, w), min(y1 + slack, h))
            self._gx, self._gy = gradient(self._gray[box[1] : box[3], box[0] : box[2]], self._sigma)
            self._box = box
        assert self._gx is not None
        assert self._gy is not None
        return self._gx, self._gy, box[0], box[1]


@functools.cache
def _neighbours(n: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Indices of the next and previous vertex of a closed polygon of ``n`` points."""
    idx = np.arange(n)
    nxt, prv = np.roll(idx, -1), np.roll(idx, 1)
    nxt.flags.writeable = False
    prv.flags.writeable = False
    return nxt, prv


# -- compiled kernels -----------------------------------------------------------------------
# A pass works on 64-element arrays, where NumPy's per-call overhead (~1-5 µs a call, ~60 calls
# a pass) was the whole cost; the kernels do the same arithmetic in one call each. They mirror
# the NumPy reference in tests/test_core_contour.py operation for operation (float32 where it
# was float32), so results agree to rounding (~1e-12 relative; the test asserts 1e-9).

_MOTION_CODE: dict[Motion, int] = {"translation": 0, "similarity": 1, "affine": 2}
# slots of the kernel's scalar output vector
_O_STATUS, _O_OK, _O_R, _O_CX, _O_CY, _O_INLIER_FRACTION = 0, 1, 2, 3, 4, 5
_O_RMS, _O_EDGE_SIGMA2, _O_CX_IN, _O_CY_IN, _O_R_IN = 6, 7, 8, 9, 10
_N_OUT = 11
# columns of the per-normal scratch array
_S_OFFSET, _S_PEAK, _S_VALID, _S_WIDTH2, _S_INTERIOR, _S_W, _S_WNEW, _S_RES = range(8)
_S_TMP, _S_TMP2 = 8, 9
_N_SCRATCH = 10
_TINY = 1e-6  # added before the log of |∇I|² (log-parabola), as in the reference
# numba types of the kernels' arrays (all C-contiguous)
_M, _M32, _V = "float64[:, ::1]", "float32[:, ::1]", "float64[::1]"


def _jit(signature: str) -> Callable[[_F], _F]:
    """Compile ``fn`` now for exactly ``signature`` (no compilation on a later call).

    ``cache=True`` reuses the machine code across processes (tests, daemon restarts) from
    ``NUMBA_CACHE_DIR``, else ``__pycache__`` next to this file, else ``~/.cache``; numba raises
    when none is writable (a read-only install without a state directory): compile in memory
    then — it only costs start-up time.
    """

    def compile_now(fn: _F) -> _F:
        try:
            kernel = numba.njit(cache=True, nogil=True, fastmath=False)(fn)
        except RuntimeError as exc:
            logger.info("numba cache not writable (%s): compiling %s in memory", exc, fn.__name__)
            kernel = numba.njit(cache=False, nogil=True, fastmath=False)(fn)
        kernel.compile(signature)
        kernel.disable_compile()
        return cast(_F, kernel)

    return compile_now


class _Workspace:
    """Preallocated arrays of one tracker's passes (no allocation per pass but the outputs)."""

    __slots__ = ("design", "mag", "mapx", "mapy", "n", "normals", "out", "scratch")

    def __init__(self, n: int, n_steps: int) -> None:
        self.n = n
        self.normals = np.empty((n, 2))
        self.mapx = np.empty((n, n_steps), dtype=np.float32)
        self.mapy = np.empty((n, n_steps), dtype=np.float32)
        self.mag = np.empty((n, n_steps), dtype=np.float32)
        self.scratch = np.empty((_N_SCRATCH, n))
        self.design = np.empty((n, 6))
        self.out = np.empty(_N_OUT)


@_jit(f"UniTuple(float64, 4)({_M}, {_M})")
def _kernel_normals(pts: FloatArray, normals: FloatArray) -> tuple[float, float, float, float]:
    """outward_normals(pts) into ``normals``; returns the bounding box (xmin, ymin, xmax, ymax)."""
    n = pts.shape[0]
    area2 = 0.0
    xmin = xmax = pts[0, 0]
    ymin = ymax = pts[0, 1]
    for i in range(n):
        nx_i = (i + 1) % n
        pv = (i - 1) % n
        tx = pts[nx_i, 0] - pts[pv, 0]
        ty = pts[nx_i, 1] - pts[pv, 1]
        norm = math.sqrt(ty * ty + tx * tx)
        norm = max(norm, 1e-12)
        normals[i, 0] = ty / norm
        normals[i, 1] = -tx / norm
        area2 += pts[i, 0] * pts[nx_i, 1] - pts[nx_i, 0] * pts[i, 1]
        xmin = min(xmin, pts[i, 0])
        xmax = max(xmax, pts[i, 0])
        ymin = min(ymin, pts[i, 1])
        ymax = max(ymax, pts[i, 1])
    if 0.5 * area2 >= 0:  # counter-clockwise in image coordinates (y down): flip to outward
        for i in range(n):
            normals[i, 0] = -normals[i, 0]
            normals[i, 1] = -normals[i, 1]
    return xmin, ymin, xmax, ymax


@_jit(f"void({_M}, {_M}, int64, float64, float64, {_M32}, {_M32})")
def _kernel_maps(  # noqa: PLR0917 - numba kernels take positional arguments
    pts: FloatArray,
    normals: FloatArray,
    s: int,
    x0: float,
    y0: float,
    mapx: npt.NDArray[np.float32],
    mapy: npt.NDArray[np.float32],
) -> None:
    """Sample positions along every normal, −s … s px, in window coordinates (float32)."""
    for i in range(pts.shape[0]):
        for j in range(2 * s + 1):
            step = float(j - s)
            mapx[i, j] = np.float32(pts[i, 0] + step * normals[i, 0] - x0)
            mapy[i, j] = np.float32(pts[i, 1] + step * normals[i, 1] - y0)


@_jit(f"int64({_M}, {_M}, float64, float64, float64, int64, {_M})")
def _kernel_design(  # noqa: PLR0917 - numba kernels take positional arguments
    pts: FloatArray,
    normals: FloatArray,
    cx: float,
    cy: float,
    scale: float,
    motion: int,
    design: FloatArray,
) -> int:
    """Normal displacement per unit motion parameter into ``design``; returns their number."""
    for i in range(pts.shape[0]):
        nx = normals[i, 0]
        ny = normals[i, 1]
        dx = (pts[i, 0] - cx) / scale
        dy = (pts[i, 1] - cy) / scale
        if motion == 0:
            design[i, 0] = nx
            design[i, 1] = ny
        elif motion == 1:  # δ = [[a, -b], [b, a]] d + t
            design[i, 0] = nx * dx + ny * dy
            design[i, 1] = ny * dx - nx * dy
            design[i, 2] = nx
            design[i, 3] = ny
        else:
            design[i, 0] = nx * dx
            design[i, 1] = nx * dy
            design[i, 2] = ny * dx
            design[i, 3] = ny * dy
            design[i, 4] = nx
            design[i, 5] = ny
    return 2 if motion == 0 else (4 if motion == 1 else 6)


@_jit(f"float64({_V})")
def _kernel_median(values: FloatArray) -> float:
    """np.median of a small 1-D array (same value)."""
    v = np.sort(values)
    m = len(v) // 2
    return float(v[m]) if len(v) % 2 else float((v[m - 1] + v[m]) / 2.0)


@_jit(f"void({_M}, {_M})")
def _kernel_resample(points: FloatArray, out: FloatArray) -> None:
    """resample_closed(points, len(out)) into ``out``."""
    m = points.shape[0]
    n = out.shape[0]
    cum = np.empty(m + 1)
    xs = np.empty(m + 1)
    ys = np.empty(m + 1)
    cum[0] = 0.0
    for i in range(m + 1):
        xs[i] = points[i % m, 0]
        ys[i] = points[i % m, 1]
        if i > 0:
            cum[i] = cum[i - 1] + math.hypot(xs[i] - xs[i - 1], ys[i] - ys[i - 1])
    total = cum[m]
    if total <= 0:
        for i in range(n):
            out[i, 0] = points[0, 0]
            out[i, 1] = points[0, 1]
        return
    s = np.empty(n)
    for i in range(n):
        s[i] = i * (total / n)
    out[:, 0] = np.interp(s, cum, xs)
    out[:, 1] = np.interp(s, cum, ys)


@_jit(f"void({_M}, {_V}, int64, {_V})")
def _kernel_solve(a: FloatArray, b: FloatArray, k: int, x: FloatArray) -> None:
    """x[:k] = solve(a[:k, :k], b[:k]) by Gaussian elimination with partial pivoting."""
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if piv != col:
            for c in range(k):
                a[col, c], a[piv, c] = a[piv, c], a[col, c]
            b[col], b[piv] = b[piv], b[col]
        for r in range(col + 1, k):
            f = a[r, col] / a[col, col]
            for c in range(col, k):
                a[r, c] -= f * a[col, c]
            b[r] -= f * b[col]
    for r in range(k - 1, -1, -1):
        acc = b[r]
        for c in range(r + 1, k):
            acc -= a[r, c] * x[c]
        x[r] = acc / a[r, r]


@_jit(f"void({_M}, int64, {_V}, {_V}, {_M}, {_V})")
def _kernel_irls(  # noqa: PLR0917 - numba kernels take positional arguments
    design: FloatArray,
    k: int,
    y: FloatArray,
    valid: FloatArray,
    scratch: FloatArray,
    params: FloatArray,
) -> None:
    """Huber-weighted least squares with a small ridge (weights, residuals into ``scratch``).

    Stops early when the weights repeat: the next solve would return the same parameters (on a
    clean edge every residual is below the Huber threshold and one re-weighting settles it).
    """
    n = design.shape[0]
    w = scratch[_S_W]
    w_new = scratch[_S_WNEW]
    res = scratch[_S_RES]
    n_valid = 0
    for i in range(n):
        w[i] = valid[i]
        res[i] = y[i]
        if valid[i] != 0:
            n_valid += 1
    ridge = RIDGE * max(float(n_valid), 1.0)
    a = np.empty((6, 6))
    b = np.empty(6)
    for _ in range(IRLS_ITERATIONS):
        nz = 0
        for i in range(n):
            if w[i] != 0:
                nz += 1
        if nz < k:
            break
        for p in range(k):
            b[p] = 0.0
            for q in range(k):
                a[p, q] = 0.0
        for i in range(n):
            wi = w[i]
            if wi == 0:
                continue
            yi = y[i] if valid[i] != 0 else 0.0
            for p in range(k):
                dp = design[i, p] * wi
                b[p] += dp * yi
                for q in range(k):
                    a[q, p] += design[i, q] * dp
        for p in range(k):
            a[p, p] += ridge
        _kernel_solve(a, b, k, params)
        same = True
        for i in range(n):
            fit = 0.0
            for c in range(k):
                fit += design[i, c] * params[c]
            res[i] = y[i] - fit
            absr = abs(res[i])
            wn = 0.0
            if valid[i] != 0:
                wn = min(1.0, HUBER_K_PX / max(absr, 1e-12))
            if absr > 2 * OUTLIER_PX:
                wn = 0.0
            w_new[i] = wn
            if wn != w[i]:
                same = False
        if same:
            break
        for i in range(n):
            w[i] = w_new[i]


@_jit(
    f"void({_M32}, {_M32}, boolean, {_M}, {_M}, float64, int64, int64, float64, {_V}, int64, "
    f"int64, {_M}, {_V}, {_M32}, {_M}, {_M}, {_V})"
)
def _kernel_fit(  # noqa: PLR0917 - numba kernels take positional arguments
    bx: npt.NDArray[np.float32],
    by: npt.NDArray[np.float32],
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
    mag: npt.NDArray[np.float32],
    scratch: FloatArray,
    design: FloatArray,
    out: FloatArray,
) -> None:
    """Peak search along the normals, robust shape-space fit, new contour (see _step)."""
    n = pts.shape[0]
    last = 2 * s
    offset = scratch[_S_OFFSET]
    peak = scratch[_S_PEAK]
    valid = scratch[_S_VALID]
    width2 = scratch[_S_WIDTH2]
    interior = scratch[_S_INTERIOR]
    tmp = scratch[_S_TMP]
    # -- per normal: sub-pixel max of |∇I|² of the target's polarity (log-parabola) --------
    if has_window:
        pol = np.float32(polarity)
        n_int = 0
        for i in range(n):
            nx32 = np.float32(normals[i, 0]) * pol
            ny32 = np.float32(normals[i, 1]) * pol
            jbest = 0
            best = np.float32(0.0)
            for j in range(last + 1):
                gx = bx[i, j]
                gy = by[i, j]
                m = gx * gx + gy * gy
                if gx * nx32 + gy * ny32 >= 0:
                    m = np.float32(0.0)  # clutter edges of the other sign are ignored
                mag[i, j] = m
                if j == 0 or m > best:
                    best = m
                    jbest = j
            jm = max(jbest - 1, 0)
            jp = min(jbest + 1, last)
            ym = float(mag[i, jm])
            y0v = float(mag[i, jbest])
            yp = float(mag[i, jp])
            inner = 0 < jbest < last
            lm = math.log(ym + _TINY)
            l0 = math.log(y0v + _TINY)
            lp = math.log(yp + _TINY)
            denom = lm - 2 * l0 + lp
            delta = 0.0
            if inner and denom < 0 and ym > 0 and yp > 0:
                delta = min(max(0.5 * (lm - lp) / denom, -0.5), 0.5)
                width2[i] = -2.0 / denom  # ln|∇I|² = c − x²/σ²: Δ² = −2/σ²
                peak[i] = math.exp(l0 - 0.25 * (lm - lp) * delta) - _TINY
            else:
                width2[i] = np.nan
                peak[i] = y0v
            offset[i] = (jbest - s) + delta
            interior[i] = 1.0 if inner else 0.0
            if inner:
                tmp[n_int] = peak[i]
                n_int += 1
        med = _kernel_median(tmp[:n_int]) if n_int > 0 else 0.0
        threshold = max(cfg[0] * med, cfg[1] ** 2)
        for i in range(n):
            valid[i] = 1.0 if interior[i] != 0 and peak[i] >= threshold else 0.0
    else:
        for i in range(n):
            offset[i] = 0.0
            peak[i] = np.nan
            valid[i] = 0.0
            width2[i] = np.nan
    # -- geometry about the centroid ---------------------------------------------------------
    cx = 0.0
    cy = 0.0
    for i in range(n):
        cx += pts[i, 0]
        cy += pts[i, 1]
    cx /= n
    cy /= n
    ss = 0.0
    for i in range(n):
        dx = pts[i, 0] - cx
        dy = pts[i, 1] - cy
        ss += dx * dx + dy * dy
    out[_O_CX_IN] = cx
    out[_O_CY_IN] = cy
    out[_O_R_IN] = math.sqrt(ss / n)
    scale = max(math.sqrt(ss / n), 1.0)
    k = _kernel_design(pts, normals, cx, cy, scale, motion, design)
    params = np.zeros(6)
    _kernel_irls(design, k, offset, valid, scratch, params)
    w = scratch[_S_W]
    res = scratch[_S_RES]
    n_in = 0
    for i in range(n):
        inl = valid[i] != 0 and abs(res[i]) <= OUTLIER_PX and w[i] > 0
        interior[i] = 1.0 if inl else 0.0  # reused: inlier flag from here on
        if inl:
            n_in += 1
    inliers = interior
    inlier_fraction = n_in / n
    out[_O_INLIER_FRACTION] = inlier_fraction
    if inlier_fraction < cfg[2]:
        out[_O_STATUS] = 1.0
        return
    out[_O_STATUS] = 0.0
    # -- apply the motion (+ a fraction of the smoothed non-rigid residual) ------------------
    moved = np.empty((n, 2))
    for i in range(n):
        dx = (pts[i, 0] - cx) / scale
        dy = (pts[i, 1] - cy) / scale
        if motion == 0:
            mx = params[0]
            my = params[1]
        elif motion == 1:
            mx = dx * params[0] + dy * -params[1] + params[2]
            my = dx * params[1] + dy * params[0] + params[3]
        else:
            mx = dx * params[0] + dy * params[1] + params[4]
            my = dx * params[2] + dy * params[3] + params[5]
        moved[i, 0] = pts[i, 0] + mx
        moved[i, 1] = pts[i, 1] + my
    if relax > 0:
        resid = scratch[_S_TMP2]
        for i in range(n):
            shift = 0.0
            for c in range(k):
                shift += design[i, c] * params[c]
            resid[i] = offset[i] - shift if inliers[i] != 0 else 0.0
        for i in range(n):
            sm = (resid[(i - 1) % n] + 2 * resid[i] + resid[(i + 1) % n]) / 4.0
            moved[i, 0] = moved[i, 0] + relax * sm * normals[i, 0]
            moved[i, 1] = moved[i, 1] + relax * sm * normals[i, 1]
    _kernel_resample(moved, new_pts)
    # -- size, plausibility, edge width, residual --------------------------------------------
    c0 = 0.0
    c1 = 0.0
    for i in range(n):
        c0 += new_pts[i, 0]
        c1 += new_pts[i, 1]
    c0 /= n
    c1 /= n
    ss = 0.0
    ok = True
    for i in range(n):
        dx = new_pts[i, 0] - c0
        dy = new_pts[i, 1] - c1
        ss += dx * dx + dy * dy
        x = new_pts[i, 0]
        y = new_pts[i, 1]
        if x < 0 or y < 0 or x >= width or y >= height:
            ok = False
    r = math.sqrt(ss / n)
    ok = ok and cfg[3] <= r <= cfg[4]
    n_w = 0
    for i in range(n):
        if inliers[i] != 0 and math.isfinite(width2[i]):
            tmp[n_w] = width2[i]
            n_w += 1
    edge_sigma2 = _kernel_median(tmp[:n_w]) if n_w >= 8 else np.nan
    if cfg[5] != 0 and math.isfinite(edge_sigma2) and r > 0:
        r += edge_sigma2 / (2.0 * r)
    rss = 0.0
    for i in range(n):
        if inliers[i] != 0:
            rss += res[i] * res[i]
            peaks[i] = peak[i]
        else:
            peaks[i] = np.nan
    out[_O_OK] = 1.0 if ok else 0.0
    out[_O_R] = r
    out[_O_CX] = c0
    out[_O_CY] = c1
    out[_O_RMS] = math.sqrt(rss / n_in)
    out[_O_EDGE_SIGMA2] = edge_sigma2
