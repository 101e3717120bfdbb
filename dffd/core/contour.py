"""Active-contour boundary tracking (docs/design.md §3, issue 4); the acquisition search that
starts it is :mod:`dffd.core.acquisition`.

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
import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core import kernel_dispatch
from dffd.core import kernel_layout as layout

FloatArray = npt.NDArray[np.float64]
Motion = Literal["translation", "similarity", "affine"]
Box = tuple[float, float, float, float]  # xmin, ymin, xmax, ymax

# Edge second moment (focus measure, dffd/core/focus.py): the window around each normal's edge is
# EDGE_WINDOW_SIGMAS times the frame's pooled edge spread, at least EDGE_WINDOW_MIN_PX; the first
# of EDGE_WINDOW_PASSES passes starts from the shape fit's edge width. Chosen on the reference
# simulator and synthetic edges (docs/estimation.md), reported on the aberrated lens.
EDGE_WINDOW_SIGMAS = 3.0
EDGE_WINDOW_MIN_PX = 2.5
EDGE_WINDOW_PASSES = 2

# Two-hypothesis prediction (ContourTracker.update): the last-position hypothesis is fitted too
# when the constant-velocity fit has fewer inliers than this fraction, or its edges lie more than
# this fraction of the normals' half-length from the prediction (a jolt; a target that moves
# smoothly is predicted within a pixel or two). Fitting both on every frame doubled the contour's
# CPU time (0.21 -> 0.48 ms a frame on a moving 40 px disc).
HYPOTHESIS_INLIERS = 0.9
HYPOTHESIS_MISS = 0.33

# Extra border of the per-frame gradient window: the passes after the first move the contour by a
# pixel or two (measured on the reference simulator), so they reuse the first pass's gradient.
GRADIENT_SLACK_PX = 4
# A pass's gradient window holds its points' box ± (search_px + this): the normals' reach plus
# the border the smoothing and the bilinear samples read.
WINDOW_MARGIN_PX = 4
# ContourTracker.start: affine passes on the acquisition frame, each adopting half the non-rigid
# residual (the coarse acquisition polygon is not yet the boundary).
START_PASSES = 6
# The polarity of a new contour: the image this far inside against this far outside it.
POLARITY_DEPTH_PX = 3.0
START_RELAX = 0.5


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
    curvature_correction: bool = True  # add σ²/(2r) to r (kernels.fit_pass)
    refine_px: float = 0.3
    # Keep the kept pass's gradient samples on each observation (``edge_samples``: the edge
    # moments' input, the focus measures other than the peak gradient); the pipeline turns it
    # off under ``peak_gradient``, where nothing reads them (five array copies a fit saved).
    edge_samples: bool = True


class EdgeSamples(NamedTuple):
    """Gradient samples along the normals of one pass, for the edge moments (focus measure)."""

    bx: npt.NDArray[np.float32]  # (Nl, 2s+1) ∂I/∂x at −s … s px along each normal
    by: npt.NDArray[np.float32]
    normals: FloatArray  # (Nl, 2) outward unit normals
    offset: FloatArray  # (Nl,) edge (peak) position along each normal, px
    inlier: FloatArray  # (Nl,) 1 for the normals the shape fit kept
    search_px: int  # s
    polarity: float  # +1: intensity drops outward
    trim_fraction: float  # of the normals dropped at each end when pooling
    sigma2_hint: float  # median log-parabola edge width², px² (first window; NaN: whole line)


class EdgeMoments(NamedTuple):
    """Per-normal edge second moments (px², NaN where unusable), their masses, the pooled cost."""

    var: FloatArray
    mass: FloatArray
    cost: tuple[float, float] | None  # (mass-weighted trimmed mean, its standard error)


def edge_moments(samples: EdgeSamples, window_sigmas: float | None = None) -> EdgeMoments:
    """Second moment of the edge-derivative profile along every inlier normal, and their pool.

    Blur variances add under convolution whatever the PSF, so the pooled moment grows as
    ``σ0² + c (v0 − v)²`` (see ``dffd.core.kernels.edge_moments`` for the adapted window of
    ``window_sigmas`` pooled spreads; None: EDGE_WINDOW_SIGMAS).
    """
    k = EDGE_WINDOW_SIGMAS if window_sigmas is None else window_sigmas
    n = len(samples.offset)
    var, mass, pooled = np.empty(n), np.empty(n), np.empty(2)
    kernel_dispatch.current().edge_moments(
        samples.bx, samples.by, samples.normals, samples.polarity, samples.search_px,
        samples.offset, samples.inlier, samples.sigma2_hint, k, EDGE_WINDOW_MIN_PX,
        EDGE_WINDOW_PASSES, samples.trim_fraction, var, mass, pooled,
    )  # fmt: skip
    cost = (float(pooled[0]), float(pooled[1])) if math.isfinite(pooled[0]) else None
    return EdgeMoments(var, mass, cost)


# Not frozen, to be treated as read-only: a frozen dataclass sets each field through
# object.__setattr__ (~4 µs for these nine on the 2-core machine), and one is built per fit.
@dataclass(slots=True)
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
    # the gradient samples along the normals of the pass kept: the focus measure's input, turned
    # into moments only when a frame's focus cost is wanted (edge_moments)
    edge_samples: EdgeSamples | None = None

    def edge_moments(self, window_sigmas: float | None = None) -> EdgeMoments | None:
        """The edge second moments of this frame and their focus cost (computed on each call;
        ``window_sigmas``: the window in pooled edge spreads, None: the default)."""
        return None if self.edge_samples is None else edge_moments(self.edge_samples, window_sigmas)


class _Fit(NamedTuple):
    """One fit (ContourTracker._fit): its observation, and what the next frame needs."""

    obs: BoundaryObservation
    failed: bool  # a pass after the first failed (the one before it was kept)
    box: Box  # of obs.points when found (xmin, ymin, xmax, ymax), else NaN
    c_in: tuple[float, float]  # centroid of the fit's input points


class ContourTracker:
    """Tracks one closed boundary frame to frame; pure given its inputs (no I/O, no clock)."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._points: FloatArray | None = None
        # the box and centroid of _points, as the kernel computed them (sequential sums, the
        # same values as NumPy's axis-0 reduction)
        self._box: Box | None = None
        self._c = (math.nan, math.nan)
        self._velocity = (0.0, 0.0)  # centroid px / s (floats: read and set every frame)
        self._t: float | None = None
        self._polarity = 1.0  # +1: intensity drops outward (bright target)
        self._bad_frames = 0
        self._ws: layout.Workspace | None = None
        # The frame a contour was started on (its time and array) and the start's observation:
        # the update on that same frame returns it (see :meth:`update`).
        self._started: tuple[float, npt.NDArray[np.uint8], BoundaryObservation] | None = None
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
    def centroid(self) -> tuple[float, float]:
        """The contour's centroid (px; predicted on a frame that failed), NaN when idle."""
        return self._c

    @property
    def bad_frames(self) -> int:
        """Consecutive frames without enough inliers."""
        return self._bad_frames

    def reset(self) -> None:
        """Drop the contour."""
        self._points = None
        self._box = None
        self._velocity = (0.0, 0.0)
        self._t = None
        self._bad_frames = 0
        self._started = None

    def start(self, gray: npt.NDArray[np.uint8], points: FloatArray, t: float) -> bool:
        """Take ``points`` (any closed polygon) as the target boundary and refine it on ``gray``."""
        pts = np.empty((self.config.n_normals, 2))
        kernel_dispatch.current().resample(np.ascontiguousarray(points, dtype=np.float64), pts)
        self._points = pts
        self._velocity = (0.0, 0.0)
        self._t = t
        self._bad_frames = 0
        self._polarity, box = self._estimate_polarity(gray, pts)
        grad = _GradientCache(gray, self.config.presmooth_sigma_px)
        # every pass must find the target: no early stop (refine_px −∞), a failed one fails;
        # the first pass's window is computed ahead from the box (no return for it)
        fit = self._fit(grad, pts, box, "affine", START_RELAX, START_PASSES, -math.inf)
        if not fit.obs.ok or fit.failed:
            self.reset()
            return False
        self._points, self._box, self._c = fit.obs.points, fit.box, fit.obs.centroid
        self._started = (t, gray, fit.obs)
        return True

    def update(
        self,
        gray: npt.NDArray[np.uint8],
        t: float,
        motion: Motion,
        head_shift: tuple[float, float] = (0.0, 0.0),
    ) -> BoundaryObservation:
        """Predict to time ``t``, measure on ``gray`` and update; raises if not active. On the
        very frame (time and array) :meth:`start` just fitted, the start's observation.

        ``head_shift``: the image motion the head's own turn since the last frame gives a
        world-fixed point at the contour (:func:`dffd.core.geometry.image_shift` of the frames'
        pan/tilt tags). The velocity is the target's own image motion, the head's taken out: when
        the head starts, stops or reverses (a drive after a search slew, a correction pulse), the
        image motion jumps by more than the normals' reach, and the prediction follows it.

        Two predictions: constant velocity, and the last position (moved by ``head_shift``) when
        the first one's fit is in doubt (not found, fewer than ``HYPOTHESIS_INLIERS`` inliers, or
        the edges more than ``HYPOTHESIS_MISS`` × ``search_px`` away from the prediction); the
        better fit is kept (:func:`better_fit`). A one-frame jitter of the image (a jolt of the
        head) throws the velocity, and the constant-velocity prediction of the next frame then
        lands beyond the normals' reach while the last position still holds the target.
        """
        if self._points is None or self._t is None or self._box is None:
            raise RuntimeError("ContourTracker.update called without an active contour")
        started, self._started = self._started, None
        if started is not None and started[0] == t and started[1] is gray:
            # The frame the contour was just started on: the start's six passes fitted it.
            # A second fit with the tracker's own model moved r by 0.001 px on the traced
            # closed-loop runs (0.5 % on one blurred first frame) and cost ~55 us an acquisition
            # (docs/design.md §10).
            return started[2]
        dt = max(t - self._t, 0.0)
        vx, vy = self._velocity
        hx, hy = head_shift
        turned = hx != 0.0 or hy != 0.0  # (a still head: exactly the values without a shift)
        sx, sy = vx * dt, vy * dt  # the constant-velocity step (floats: NumPy's arithmetic)
        still_points, still_box = self._points, self._box
        if turned:
            sx, sy = sx + hx, sy + hy
            still_points = self._points + np.array([hx, hy])
            bx0, by0, bx1, by1 = self._box
            still_box = (bx0 + hx, by0 + hy, bx1 + hx, by1 + hy)
        predicted = self._points + np.array([sx, sy])
        # the predicted box, exactly: rounding is monotonic, so min(x + s) = min(x) + s
        xmin, ymin, xmax, ymax = self._box
        box_pred = (xmin + sx, ymin + sy, xmax + sx, ymax + sy)
        relax = self.config.relax if motion != "translation" else 0.0
        grad = _GradientCache(gray, self.config.presmooth_sigma_px)
        passes, refine = self.config.max_passes, self.config.refine_px
        fit = first = self._fit(grad, predicted, box_pred, motion, relax, passes, refine)
        if math.hypot(sx, sy) > refine and self._in_doubt(first.obs, first.c_in):
            still = self._fit(grad, still_points, still_box, motion, relax, passes, refine)
            if better_fit(still.obs, first.obs):
                fit = still
        obs = fit.obs
        if obs.ok:
            if dt > 0:
                ox, oy = self._c
                nx, ny = obs.centroid
                if turned:
                    ox, oy = ox + hx, oy + hy
                # alpha-filtered velocity: a single noisy frame must not throw the prediction
                self._velocity = (
                    0.6 * vx + 0.4 * (nx - ox) / dt,
                    0.6 * vy + 0.4 * (ny - oy) / dt,
                )
            self._points, self._box, self._c = obs.points, fit.box, obs.centroid
            self._bad_frames = 0
        else:
            self._points, self._box, self._c = predicted, box_pred, first.c_in
            self._bad_frames += 1
        self._t = t
        return obs

    def seed_velocity(
        self, t_seen: float, seen_px: tuple[float, float], head_shift: tuple[float, float]
    ) -> None:
        """A contour just started on a target seen at ``seen_px`` at ``t_seen`` (before a short
        loss): start from the velocity between the two sightings, the head's own turn between
        them (``head_shift``) taken out. A target re-acquired while it crosses the image faster
        than the normals' reach per frame is otherwise lost again on the next frame."""
        if self._t is None or not self._t > t_seen:
            return
        dt = self._t - t_seen
        cx, cy = self._c
        self._velocity = (
            (cx - seen_px[0] - head_shift[0]) / dt,
            (cy - seen_px[1] - head_shift[1]) / dt,
        )

    @property
    def lost(self) -> bool:
        """True once too many consecutive frames failed."""
        return self._bad_frames >= self.config.lost_after_frames

    def _in_doubt(self, obs: BoundaryObservation, c_pred: tuple[float, float]) -> bool:
        """A fit worth checking against the other prediction (see :meth:`update`); ``c_pred``:
        the centroid of the prediction."""
        if not obs.ok or obs.inlier_fraction < HYPOTHESIS_INLIERS:
            return True
        miss = math.hypot(obs.centroid[0] - c_pred[0], obs.centroid[1] - c_pred[1])
        return miss > HYPOTHESIS_MISS * self.config.search_px

    def _fit(  # noqa: PLR0917 - one fit's parameters
        self,
        grad: _GradientCache,
        predicted: FloatArray,
        box: Box | None,
        motion: Motion,
        relax: float,
        max_passes: int,
        refine_px: float,
    ) -> _Fit:
        """Fit the contour from ``predicted`` (its ``box`` if known): search again along the
        updated contour while a pass moves it by more than ``refine_px`` (at most
        ``max_passes`` passes); the observation of the last good pass.

        One call of the ``fit_passes`` kernel does every pass (:mod:`dffd.core.kernels`, or its
        NumPy twin while numba compiles: :mod:`dffd.core.kernel_dispatch`); it returns early
        only when a pass needs a gradient window the frame's cache does not hold, which is
        computed here before the kernel resumes (the first pass's window is computed ahead
        when ``box`` is given). The NumPy reference pass is kept in tests/test_core_contour.py,
        which checks the kernels against it.
        """
        cfg = self.config
        pts = np.ascontiguousarray(predicted, dtype=np.float64)
        n = len(pts)
        ws = self._workspace(n)
        state = ws.state
        state.fill(0)
        state[layout.ST_KEPT] = -1
        kernels = kernel_dispatch.current()  # one implementation for the whole fit
        s = cfg.search_px
        margin = s + WINDOW_MARGIN_PX
        h, w = grad.shape
        if box is not None:
            grad.window(*box, margin)  # the window the kernel's first pass will ask for
        code = layout.MOTION_CODE[motion]
        while True:
            kernels.fit_passes(
                grad.gx, grad.gy, grad.win, pts, self._polarity, s, code, relax, self._cfg_vec,
                w, h, max_passes, refine_px, margin, state, ws.normals, ws.bx, ws.by, ws.mag,
                ws.new_pts, ws.peaks, ws.scratch, ws.design, ws.out, ws.fit,
            )  # fmt: skip
            if not state[layout.ST_NEED_WINDOW]:
                break
            b = layout.ST_BOX
            x0, y0, x1, y1 = state[b : b + 4].tolist()
            grad.cover(x0, y0, x1, y1)
        st = state.tolist()
        kept = st[layout.ST_KEPT]
        failed = st[layout.ST_FAILED] != 0
        res = ws.out[kept].tolist()  # the kernel's scalars as floats at once
        xmin, ymin, xmax, ymax, cx_in, cy_in = ws.fit.tolist()
        c_in = (cx_in, cy_in)
        inlier_fraction = res[layout.OUT_INLIER_FRACTION]
        if res[layout.OUT_STATUS] != 0:  # only a first pass is kept without enough inliers
            bad = _bad(pts, c_in, res[layout.OUT_R_IN], n, inlier_fraction)
            return _Fit(bad, failed, (xmin, ymin, xmax, ymax), c_in)
        edge_sigma2 = res[layout.OUT_EDGE_SIGMA2]
        ok = res[layout.OUT_OK] != 0
        samples = None
        if ok and cfg.edge_samples and st[layout.ST_HAS_WINDOW + kept]:
            # the focus measure's input: the gradient samples of the pass kept (copies: the
            # workspace is reused by the next fit)
            scratch = ws.scratch[kept]
            samples = EdgeSamples(
                ws.bx[kept].copy(), ws.by[kept].copy(), ws.normals[kept].copy(),
                scratch[layout.SCRATCH_OFFSET].copy(), scratch[layout.SCRATCH_INLIER].copy(), s,
                self._polarity, cfg.trim_fraction, edge_sigma2,
            )  # fmt: skip
        obs = BoundaryObservation(
            points=ws.new_pts[kept].copy(),
            centroid=(res[layout.OUT_CX], res[layout.OUT_CY]),
            r_px=res[layout.OUT_R],
            peak_sq=ws.peaks[kept].copy(),
            inlier_fraction=inlier_fraction,
            residual_px=res[layout.OUT_RMS],
            ok=ok,
            edge_sigma_px=math.sqrt(edge_sigma2) if math.isfinite(edge_sigma2) else math.nan,
            edge_samples=samples,  # only a found contour carries them
        )
        return _Fit(obs, failed, (xmin, ymin, xmax, ymax), c_in)

    def _workspace(self, n: int) -> layout.Workspace:
        ws = self._ws
        if ws is None or ws.n != n:
            ws = self._ws = layout.Workspace(n, 2 * self.config.search_px + 1)
        return ws

    def _estimate_polarity(self, gray: npt.NDArray[np.uint8], pts: FloatArray) -> tuple[float, Box]:
        """+1 when the inside is brighter 3 px either side of the boundary (median over normals;
        one kernel call: ~40 -> ~5 us at acquisition), and the box of ``pts``."""
        img = gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
        normals = self._workspace(len(pts)).normals[0]
        kernels = kernel_dispatch.current()
        box = kernels.normals_and_box(pts, normals)
        pol = kernels.polarity(np.ascontiguousarray(img), pts, normals, POLARITY_DEPTH_PX)
        return pol, box


# -- geometry helpers (public: the pipeline and tests use them) -----------------------------
def gradient(
    patch: npt.NDArray[np.uint8], presmooth_sigma_px: float
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Image gradient (gray levels / px) of a gray or BGR patch after Gaussian smoothing."""
    gray = cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY) if patch.ndim == 3 else patch
    img = np.asarray(gray, dtype=np.float32)
    if presmooth_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), presmooth_sigma_px), dtype=np.float32)
    # Sobel 3x3 sums 8x the per-pixel derivative; both in one pass (cv2.Sobel's values)
    gx = np.empty_like(img)
    gy = np.empty_like(img)
    kernel_dispatch.current().sobel_pair(img, gx, gy)
    return gx, gy


def better_fit(a: BoundaryObservation, b: BoundaryObservation) -> bool:
    """True when ``a`` fits the image better than ``b``: found where ``b`` is not, else more
    inlier normals, else (as many) a smaller RMS residual."""
    if a.ok != b.ok:
        return a.ok
    if a.inlier_fraction != b.inlier_fraction:
        return a.inlier_fraction > b.inlier_fraction
    return a.residual_px < b.residual_px


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
    """Rotation-invariant image size r = sqrt(tr Σ) of boundary points (docs/design.md §3)."""
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


class _GradientCache:
    """The pre-smoothed gradient of one frame around the target, computed once per frame.

    The passes of one update search nearly the same neighbourhood: the window is grown by
    ``GRADIENT_SLACK_PX`` so that the following passes (the contour moves by a pixel or two)
    reuse it; a pass that leaves it recomputes a window around its own contour. ``win`` holds
    the window's corners in the frame (x0, y0, x1, y1; all 0 before the first), ``gx``, ``gy``
    its gradient.
    """

    __slots__ = ("_sigma", "gray", "gx", "gy", "shape", "win")

    def __init__(self, gray: npt.NDArray[np.uint8], presmooth_sigma_px: float) -> None:
        self.gray = gray
        self._sigma = presmooth_sigma_px
        self.win = np.zeros(layout.N_WIN, dtype=np.int64)
        self.gx: npt.NDArray[np.float32] = _NO_WINDOW
        self.gy: npt.NDArray[np.float32] = _NO_WINDOW
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
        self.cover(x0, y0, x1, y1)
        return self.gx, self.gy, int(self.win[0]), int(self.win[1])

    def cover(self, x0: int, y0: int, x1: int, y1: int) -> None:
        """Make the window hold the frame's box [x0, x1) × [y0, y1) (recomputed if it does not)."""
        bx0, by0, bx1, by1 = self.win.tolist()
        if x0 < bx0 or y0 < by0 or x1 > bx1 or y1 > by1 or bx1 <= bx0:
            h, w = self.shape
            slack = GRADIENT_SLACK_PX
            box = (max(x0 - slack, 0), max(y0 - slack, 0), min(x1 + slack, w), min(y1 + slack, h))
            self.gx, self.gy = gradient(self.gray[box[1] : box[3], box[0] : box[2]], self._sigma)
            self.win[:] = box


_NO_WINDOW: npt.NDArray[np.float32] = np.zeros((0, 0), dtype=np.float32)


@functools.cache
def _neighbours(n: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Indices of the next and previous vertex of a closed polygon of ``n`` points."""
    idx = np.arange(n)
    nxt, prv = np.roll(idx, -1), np.roll(idx, 1)
    nxt.flags.writeable = False
    prv.flags.writeable = False
    return nxt, prv
