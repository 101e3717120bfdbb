"""The procedure of ``dffd calibrate`` on any rig: the capture latency, a focus sweep per depth,
the lens table fitted and checked, the depths it flags swept again.

One procedure (:func:`calibrate`, :func:`calibrate_table`) runs against a :class:`Rig` — the
simulated camera or the real one (:mod:`dffd.calibrate_rigs`); only the rig differs, the sweep,
the fit and the file written are the same code.

Capture latency (first, at the first depth). The focus is settled, a few frames give the image
noise floor, then a focus step is commanded and the frames delivered after the command that still
show the old focus are counted: the frames in flight → ``[capture] latency_frames``
(:func:`measure_latency`).

Focus table. The target is placed at each known depth z (on the real camera an operator places
it and presses Enter at the terminal prompt). The focus is swept coarse over the whole range,
then fine around the sharpest setting, :data:`FRAMES_PER_SETTING` frames at each fine setting
(averaged; their spread gives the cost's σ); every sample is a frame exposed entirely after the
focus move completed (latency + 2 frames after the VISCA Completion) (:func:`sharpest`). The
focus cost is taken exactly as the estimator takes it — active contour normals and the
configured ``[estimators] focus_measure`` (:func:`dffd.core.focus.frame_cost`) — so whatever bias
the measure has on this lens is absorbed by the table, as the estimator's bursts will see it.
The first vertex of a sweep is a parabola fitted on a window, symmetric about the vertex, where
the cost is parabolic (:func:`dffd.calibrate_parabola.fit_vertex`). The thin lens gives each
depth its focus power ``P = 1/z``; a smooth model ``P(counts)`` (a polynomial and a residual
spline, their structure chosen by cross-validation, outliers dropped:
:func:`dffd.calibrate_model.fit_focus_model`) is fitted to the depths; then each sweep is read
where the estimator's closed loop settles on it (the burst bracket whose ends cost the same,
:mod:`dffd.calibrate_vertex`) and the model refitted through the ends of those brackets
(:func:`dffd.calibrate_fit.fit_table`), until they stop moving. The file written tabulates
``v = 1/(1/f − P)`` of the model densely over the focus range (PCHIP-interpolated by
:class:`dffd.core.lens.Lens`); where each depth was read and the model's residuals are printed.
:func:`calibrate_table` runs the procedure, fits the table and checks it
(:func:`dffd.calibrate_check.check_table`: the table's σ per depth, the depths to sweep again),
repeating the sweeps the check asks for.

Split from :mod:`dffd.calibrate` (the command, which runs this on a rig and writes the file).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from dffd.calibrate_check import MAX_SWEEPS, TableCheck, check_table, table_sigma_per_depth
from dffd.calibrate_fit import VERTEX_WINDOW_BLUR_PX, TableFit, fit_table
from dffd.calibrate_parabola import fit_vertex
from dffd.calibrate_types import CalibrationError, DepthPoint, FocusOptics
from dffd.calibrate_vertex import table_response
from dffd.core.acquisition import find_target
from dffd.core.contour import ContourTracker, TrackerConfig
from dffd.core.focus import DEFAULT_FOCUS_MEASURE, PlanConfig, frame_cost
from dffd.core.lens import MM_PER_M
from dffd.literals import FocusMeasure

_LOGGER = logging.getLogger(__name__)


COARSE_POINTS = 33  # focus settings of the coarse sweep over the whole range
# The fine sweep: FINE_POINTS settings over ± FINE_SPAN_STEPS coarse steps around the coarse
# minimum — wide enough to hold the estimator's burst bracket (± 3 px of blur, ~90 µm of v) on
# both sides of the vertex even at 20 m, where ~70 counts are a micrometre of v.
FINE_POINTS = 41
FINE_SPAN_STEPS = 7
# Frames averaged at each fine setting: a single frame's vertex scatters by ~1 µm of v (0.1 m of
# depth at 10 m); four cut that in half and their spread gives the cost's σ.
FRAMES_PER_SETTING = 4
# Image change: the largest change of an 8×8 block mean between two frames (a refocused edge
# changes its blocks by tens of DN; averaging cuts the pixel noise 8×). "Changed" means more than
# CHANGE_THRESHOLD_DN and NOISE_FACTOR × the largest such change between frames at rest.
CHANGE_BLOCK_PX = 8
CHANGE_THRESHOLD_DN = 0.5
NOISE_FACTOR = 3.0
NOISE_FRAMES = 4  # frames at the settled focus that give the noise floor
LATENCY_MAX_FRAMES = 20  # give up counting after this many frames
# Frames beyond the latency to wait after a Completion before a frame surely exposed after it.
SETTLE_EXTRA_FRAMES = 2

Image = npt.NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class CalibrationResult:
    """The fitted table, its check (σ per depth, what was swept again) and the latency."""

    table: TableFit
    check: TableCheck | None  # None with fewer depths than a focus model needs
    latency_frames: int
    points: tuple[DepthPoint, ...]  # every sweep's point, repeats included
    repeated: tuple[float, ...]  # depths swept more than once, in the order swept again
    # how the burst fit's vertex responds to the true offset on these sweeps (written into the
    # lens file as ``table.lens.vertex_response``; dffd.calibrate_vertex.table_response)
    response_lines: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """The residuals and the uncertainty per depth, the repeats (CLI and lens file)."""
        out = self.table.residual_lines()
        if self.check is not None:
            out += self.check.lines()
        if self.repeated:
            out.append(
                "swept again (predicted beyond the leave-one-out limit by the other depths): "
                + ", ".join(f"{z:g} m" for z in self.repeated)
            )
        out += self.response_lines
        return out


class Rig(FocusOptics, Protocol):
    """A camera with a controllable focus and a frame source, and a way to place the target."""

    async def place_target(self, z_m: float) -> None:
        """Have the (static) target at ``z_m`` metres on the optical axis."""
        ...

    async def frame_at(self, counts: int, settle_frames: int) -> Image:
        """Move the focus to ``counts``; a gray frame exposed entirely after it settled."""
        ...

    async def step_focus(self, counts: int) -> float:
        """Command a focus move without waiting; the monotonic time it was written."""
        ...

    async def next_frame(self) -> tuple[Image, float]:
        """The next delivered gray frame and its delivery time (same clock as step_focus)."""
        ...


async def calibrate(
    rig: Rig,
    depths: list[float],
    measure: FocusMeasure = DEFAULT_FOCUS_MEASURE,
    swept: list[DepthPoint] | None = None,
) -> tuple[list[DepthPoint], int]:
    """The procedure on any rig: the capture latency, then the sharpest setting per depth
    (with the estimator's focus ``measure``). Each point is appended to ``swept`` (the list
    returned) as its sweep ends: what a stopped procedure had measured."""
    await rig.place_target(depths[0])
    latency = await measure_latency(rig)
    settle = latency + SETTLE_EXTRA_FRAMES
    points = swept if swept is not None else []
    for i, z in enumerate(depths):
        if i:
            await rig.place_target(z)
        points.append(await sharpest(rig, z, settle, measure))
        _LOGGER.info("z = %.3f m: sharpest at %.1f counts", z, points[-1].at)
    return points, latency


async def calibrate_table(
    rig: Rig,
    depths: list[float],
    measure: FocusMeasure = DEFAULT_FOCUS_MEASURE,
    name: str = "calibrated",
    swept: list[DepthPoint] | None = None,
) -> CalibrationResult:
    """:func:`calibrate`, the table fitted, and the depths its check flags swept again (each at
    most MAX_SWEEPS times; :mod:`dffd.calibrate_check`) until none is flagged; every sweep's
    point is appended to ``swept`` as it ends."""
    points, latency = await calibrate(rig, depths, measure, swept)
    f_number = getattr(rig, "f_number", None)
    settle = latency + SETTLE_EXTRA_FRAMES
    repeated: list[float] = []
    # each round sweeps again what the check flags; a depth is flagged only while it has had
    # fewer than MAX_SWEEPS sweeps, so the rounds end (a flagged neighbour can delay a third
    # sweep of the depth that pulled it by a round)
    for _ in range(2 * MAX_SWEEPS):
        table = fit_table(name, rig, points, f_number)
        check = check_table(table, rig) if table.fit is not None else None
        if check is None or not check.repeat:
            break
        for z in check.repeat:
            _LOGGER.info("z = %.3f m: the other depths predict it badly; sweeping it again", z)
            await rig.place_target(z)
            points.append(await sharpest(rig, z, settle, measure))
            repeated.append(z)
    else:
        table = fit_table(name, rig, points, f_number)
        check = check_table(table, rig) if table.fit is not None else None
    # the burst fit's vertex against the true offset, on the same sweeps through this table
    # (docs/estimation.md §21): the estimator inverts it to correct each burst's vertex
    response, lines = table_response(
        table.lens,
        [(p.placed_m, p.sweep) for p in points],
        measure,
        VERTEX_WINDOW_BLUR_PX,
        PlanConfig().default_f_number,
    )
    if response is not None:
        table = dataclasses.replace(
            table, lens=dataclasses.replace(table.lens, vertex_response=response)
        )
    if check is not None:
        # the table's σ where each depth is (docs/estimation.md §25), not one number
        per_depth = table_sigma_per_depth(table, check)
        table = dataclasses.replace(
            table, lens=dataclasses.replace(table.lens, table_sigma_v_at=per_depth)
        )
    return CalibrationResult(table, check, latency, tuple(points), tuple(repeated), tuple(lines))


async def sharpest(
    rig: Rig,
    z_m: float,
    settle_frames: int,
    measure: FocusMeasure = DEFAULT_FOCUS_MEASURE,
    frames: int | None = None,
) -> DepthPoint:
    """Sweep the focus with the target at ``z_m``; the sharpest counts and its v (``frames``
    averaged per fine setting; None: FRAMES_PER_SETTING)."""
    frames = FRAMES_PER_SETTING if frames is None else frames
    lo, hi = rig.focus_range
    coarse = np.linspace(lo, hi, COARSE_POINTS)
    costs, _, sizes = await _costs(rig, coarse, settle_frames, measure, 1)
    if not np.isfinite(costs).any():
        raise CalibrationError(f"target not found at {z_m} m at any focus; " + _why_not(sizes))
    best = float(coarse[int(np.nanargmin(costs))])
    span = FINE_SPAN_STEPS * (hi - lo) / (COARSE_POINTS - 1)
    fine = np.linspace(max(lo, best - span), min(hi, best + span), FINE_POINTS)
    fine_costs, fine_sigma, fine_sizes = await _costs(rig, fine, settle_frames, measure, frames)
    ok = np.isfinite(fine_costs)
    found = fit_vertex(fine, fine_costs, fine_sigma) if ok.sum() >= 3 else None
    if found is None:
        raise CalibrationError(
            f"target not measurable at {z_m} m (a contour at {ok.sum()} of {FINE_POINTS} "
            "settings around the sharpest, or no minimum among them); "
            + _why_not(sizes + fine_sizes)
        )
    f = rig.focal_length_mm
    z = z_m * MM_PER_M
    sweep = tuple(
        (float(c), float(g), float(s))
        for c, g, s in zip(fine[ok], fine_costs[ok], fine_sigma[ok], strict=True)
    )
    return DepthPoint(
        z_m, round(found.x), f * z / (z - f), float(np.nanmin(fine_costs)),
        found.x, found.sigma, sweep,
    )  # fmt: skip


async def measure_latency(rig: Rig) -> int:
    """Frames delivered after a focus step before one shows it (the frames in flight)."""
    lo, hi = rig.focus_range
    prev = _blocks(await rig.frame_at(lo + (hi - lo) // 2, LATENCY_MAX_FRAMES))
    noise = 0.0
    for _ in range(NOISE_FRAMES):
        image = _blocks((await rig.next_frame())[0])
        noise = max(noise, float(np.abs(image - prev).max()))
        prev = image
    threshold = max(CHANGE_THRESHOLD_DN, NOISE_FACTOR * noise)
    t_cmd = await rig.step_focus(lo)
    in_flight = 0
    for _ in range(LATENCY_MAX_FRAMES):
        frame, delivered = await rig.next_frame()
        image = _blocks(frame)
        if delivered >= t_cmd:
            if float(np.abs(image - prev).max()) > threshold:
                return in_flight
            in_flight += 1
        prev = image
    raise CalibrationError(
        f"the image never changed after a focus step (threshold {threshold:.2f} DN); is the "
        "target in view and the camera in manual focus?"
    )


# -- private helpers --------------------------------------------------------------------------
def _blocks(image: Image) -> npt.NDArray[np.float64]:
    """Means of CHANGE_BLOCK_PX² blocks (the image cropped to whole blocks)."""
    b = CHANGE_BLOCK_PX
    h, w = image.shape[0] // b * b, image.shape[1] // b * b
    cropped = image[:h, :w].astype(np.float64)
    means: npt.NDArray[np.float64] = cropped.reshape(h // b, b, w // b, b).mean(axis=(1, 3))
    return means


async def _costs(
    rig: Rig,
    settings: npt.NDArray[np.float64],
    settle: int,
    measure: FocusMeasure,
    frames: int,
) -> tuple[npt.NDArray[Any], npt.NDArray[Any], list[float]]:
    """The focus cost at each setting, averaged over ``frames`` frames (NaN: no contour), the σ
    of that mean, and the radii (px) of the blobs found where the contour could not start."""
    out = np.full(len(settings), np.nan)
    sigma = np.full(len(settings), np.nan)
    tracker = ContourTracker(TrackerConfig())
    refused: list[float] = []
    t = 0.0
    for i, c in enumerate(settings):
        values: list[float] = []
        errors: list[float] = []
        for k in range(frames):
            gray = (
                await rig.frame_at(round(float(c)), settle)
                if k == 0
                else (await rig.next_frame())[0]
            )
            t += 1.0
            poly = find_target(gray)
            if poly is None:
                continue
            if not tracker.start(gray, poly, t):
                refused.append(_radius_px(poly))
                continue
            cost = frame_cost(tracker.update(gray, t, "translation"), measure)
            if cost is not None:
                values.append(cost[0])
                errors.append(cost[1])
        if values:
            out[i] = float(np.mean(values))
            # the larger of the frames' own σ and their spread, for the mean
            spread = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
            sigma[i] = max(spread, float(np.mean(errors))) / math.sqrt(len(values))
    return out, sigma, refused


def _radius_px(poly: npt.NDArray[np.float64]) -> float:
    """The size measure r = sqrt(tr Σ) of a boundary polygon, in pixels."""
    pts = np.asarray(poly, dtype=np.float64)
    return float(np.sqrt(np.trace(np.cov(pts.T, bias=True))))


def _why_not(refused_radii: list[float]) -> str:
    limits = TrackerConfig()
    if refused_radii and max(refused_radii) > limits.max_radius_px:
        return (
            f"a blob of radius {max(refused_radii):.0f} px was seen, larger than the tracker "
            f"takes ({limits.max_radius_px:.0f} px): place the target further away or use a "
            "smaller one"
        )
    if refused_radii:
        return (
            f"a blob of radius {max(refused_radii):.0f} px was seen but its edge could not be "
            "followed: check the lighting and that the target is the only high-contrast object"
        )
    return "check that it is in view, centred and lit"


__all__ = [
    "CalibrationResult",
    "Image",
    "Rig",
    "calibrate",
    "calibrate_table",
    "measure_latency",
    "sharpest",
]
