"""``dffd calibrate``: fit the focus counts ↔ v table; the capture latency (design.md §3, §5).

One procedure (:func:`calibrate`) runs against a :class:`Rig` — the simulated camera
(``--sim``: :class:`SimRig`, lock-step virtual time) or the real camera (:class:`LabRig`: the
VISCA camera on ``camera.port`` and the video device ``capture.device`` of ``--config``). Only the
rig differs; the sweep, the fit and the file written are the same code.

Capture latency in seconds for network video: ``dffd calibrate --latency --config FILE``
(:mod:`dffd.latency`).

Capture latency (first, at the first depth). The focus is settled, a few frames give the image
noise floor, then a focus step is commanded and the frames delivered after the command that still
show the old focus are counted: the frames in flight → ``[capture] latency_frames``.

Focus table. The target is placed at each known depth z (``--depths``; on the real camera an
operator places it and presses Enter at the terminal prompt). The focus is swept coarse over the
whole range, then fine around the sharpest setting, :data:`FRAMES_PER_SETTING` frames at each
fine setting (averaged; their spread gives the cost's σ); every sample is a frame exposed
entirely after the focus move completed (latency + 2 frames after the VISCA Completion). The
focus cost is taken exactly as the estimator takes it — active contour normals and the
configured ``[estimators] focus_measure`` (:func:`dffd.core.focus.frame_cost`) — so whatever bias
the measure has on this lens is absorbed by the table, as the estimator's bursts will see it.
The first vertex of a sweep is a parabola fitted on a window, symmetric about the vertex, where
the cost is parabolic (:func:`dffd.calibrate_fit.fit_vertex`). The thin lens gives each depth
its focus power ``P = 1/z``; a smooth model ``P(counts)`` (a polynomial and a residual spline,
their structure chosen by cross-validation, outliers dropped:
:func:`dffd.calibrate_fit.fit_focus_model`) is fitted to the depths; then each sweep is read
where the estimator's closed loop settles on it (the burst bracket whose ends cost the same,
:mod:`dffd.calibrate_vertex`) and the model refitted through the ends of those brackets
(:func:`dffd.calibrate_fit.fit_table`), until they stop moving. The file written tabulates
``v = 1/(1/f − P)`` of the model densely over the focus range (PCHIP-interpolated by
:class:`dffd.core.lens.Lens`); where each depth was read and the model's residuals are printed.
:func:`calibrate_table` runs the procedure, fits the table and checks it
(:func:`dffd.calibrate_check.check_table`: the table's σ per depth, the depths to sweep again),
repeating the sweeps the check asks for.

Lab procedure (real camera):

1. Mount the camera, set the zoom used in service (``[lens] zoom_counts`` or the lens file's),
   light the target evenly; the target must be the only high-contrast blob in view, centred.
2. ``dffd calibrate --config /etc/dffd/dffd.toml --out /etc/dffd/lenses/NEW.toml`` (the
   default depths: :data:`DEFAULT_DEPTHS_M`, denser where the table curves and at long range,
   where a micrometre of v is a decimetre of depth) — the config names ``camera.port``,
   ``capture.device`` (and its size/fps/fourcc) and ``lens.file``: when that file exists its
   focal length, pixel pitch and f-number are reused (f is fixed at a fixed zoom); when it does
   not (the table this calibration writes), those of the packaged default lens
   (:data:`dffd.resources.DEFAULT_LENS`), with a note to check them. ``--out``'s directory must
   exist and be writable: it is checked before the first depth. Run it from an interactive
   terminal: without one on stdin (systemd, a pipe, ``</dev/null``) nobody can answer its
   prompts, and it refuses to start (:mod:`dffd.calibrate_operator`).
3. At each prompt place the target at that depth along the optical axis (measure from the
   front principal plane; ±5 mm matters at 1 m) and press Enter (keys typed before the prompt
   are dropped; Ctrl-C or Ctrl-D stops, saying how many depths were measured: they are not kept,
   no table is written). About a minute per depth. A depth the other depths predict badly
   (beyond ``REPEAT_SIGMA`` σ of the table fitted without it, :mod:`dffd.calibrate_check`) is
   asked for again at the end, and a third time while its two sweeps disagree; the output
   gives the table's own 1σ per depth (µm of v, mm of depth).
4. Set ``[lens] file`` to the new table and ``[capture] latency_frames`` to the printed latency.

Exit codes: 0 written, 1 the procedure failed (target not found, non-monotone, camera), 2 usage
(also the lab procedure without a terminal), 130 stopped by the operator (Ctrl-C; Ctrl-D at a
prompt).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import logging
import math
import os
import stat
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from dffd.calibrate_check import MAX_SWEEPS, TableCheck, check_table, table_sigma_per_depth
from dffd.calibrate_fit import (
    VERTEX_WINDOW_BLUR_PX,
    CalibrationError,
    DepthPoint,
    FocusOptics,
    TableFit,
    fit_table,
    fit_vertex,
)
from dffd.calibrate_operator import InputEndedError, ask_operator, stopped_message, terminal_problem
from dffd.calibrate_vertex import table_response
from dffd.cli.loading import say_if_compiling
from dffd.config import ConfigError, DffdConfig, load_config, missing_devices
from dffd.core import kernel_dispatch
from dffd.core.acquisition import find_target
from dffd.core.contour import ContourTracker, TrackerConfig
from dffd.core.focus import DEFAULT_FOCUS_MEASURE, PlanConfig, frame_cost
from dffd.core.lens import MM_PER_M, Lens, LensError, VertexResponse
from dffd.exitcodes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from dffd.literals import FocusMeasure
from dffd.resources import DEFAULT_LENS, lens_table
from drivers.sim.resources import reference_camera_file

_LOGGER = logging.getLogger(__name__)


# Default depths (m): about even in v (the focus cam's curvature) and denser at long range, where
# one micrometre of v is ~0.1 m of depth and the table must be measured, not interpolated. Every
# 0.25-0.75 m over 2-10 m (23 depths, was 15): the 7-10 m brackets' far ends measure the table
# near infinity, where the estimator reads a far target, so more of them average its noise. Chosen
# on the reference optics (tables 4.8/4.1/2.6 -> 2.6/1.9/1.2 mm rms, docs/estimation.md §18);
# about 8 more minutes at the lab's ~1 minute a depth.
DEFAULT_DEPTHS_M = (
    1.0, 1.5, 2.0, 2.25, 2.5, 2.75, 3.0, 3.25, 3.5, 4.0, 4.5, 5.0, 5.5, 6.25, 7.0, 7.75, 8.5,
    9.25, 10.0, 12.0, 14.0, 17.0, 20.0,
)  # fmt: skip
# The contour must fit the tracker's radius range with room to spare: at most this fraction of
# TrackerConfig.max_radius_px (its normals search ±search_px beyond the edge, and a target that
# nearly fills the frame leaves the background too little area for the threshold), at least
# MIN_RADIUS_MARGIN × min_radius_px (a few-pixel blob gives a noisy focus cost).
MAX_RADIUS_FRACTION = 0.9
MIN_RADIUS_MARGIN = 1.5
DEPTH_STEP_M = 0.1  # a default depth the target is too large at moves out to a multiple of this
COARSE_POINTS = 33  # focus settings of the coarse sweep over the whole range
# The fine sweep: FINE_POINTS settings over ± FINE_SPAN_STEPS coarse steps around the coarse
# minimum — wide enough to hold the estimator's burst bracket (± 3 px of blur, ~90 µm of v) on
# both sides of the vertex even at 20 m, where ~70 counts are a micrometre of v.
FINE_POINTS = 41
FINE_SPAN_STEPS = 7
# Frames averaged at each fine setting: a single frame's vertex scatters by ~1 µm of v (0.1 m of
# depth at 10 m); four cut that in half and their spread gives the cost's σ.
FRAMES_PER_SETTING = 4
FIT_HALF_WIDTH = 3  # points either side of the minimum used by vertex() (the coarse peak)
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
# Camera initialisation (the D100 takes ~10 s from standby, docs/design.md §6) and one focus move.
CAMERA_INIT_TIMEOUT_S = 30.0
# A frame must arrive within this time from a V4L2 device (30 fps; a grabber may stall ~1 s).
FRAME_TIMEOUT_S = 2.0

# The simulated camera keeps running between placements: a depth placed again is rendered from
# this many frames further on (new sensor noise; a sweep is ~250 frames).
SIM_REPEAT_FRAMES = 100_000

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


def run(args: argparse.Namespace) -> int:
    """Calibrate; print the table and the latency; return the exit code."""
    if getattr(args, "latency", False):
        from dffd.latency import run as run_latency

        return run_latency(args)
    try:
        text = args.depths or ",".join(str(z) for z in DEFAULT_DEPTHS_M)
        depths = sorted({float(z) for z in text.split(",") if z.strip()})
    except ValueError:
        print(f"dffd calibrate: --depths {args.depths!r} is not a list of numbers", file=sys.stderr)
        return EXIT_USAGE
    if len(depths) < 2 or min(depths) <= 0:
        print("dffd calibrate: give at least two positive depths", file=sys.stderr)
        return EXIT_USAGE
    if args.sim == (args.config is not None):
        print(
            "dffd calibrate: give either --sim (simulated camera) or --config FILE (the real "
            "camera on FILE's camera.port and capture.device)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    # Everything that can be checked is, before the procedure (minutes; ~1 a depth in the lab)
    # and before the kernels load (a first start compiles them: 20-40 s).
    unwritable = output_problem(args.out) if args.out is not None else None
    if unwritable is not None:
        print(f"dffd calibrate: {unwritable}", file=sys.stderr)
        return EXIT_USAGE
    swept: list[DepthPoint] = []  # each sweep's point as it ends: what a stop had measured
    if args.sim:
        sim_rig = SimRig(args.sim_config or reference_camera_file())
        if args.depths is None:
            depths = sim_rig.usable_depths(DEFAULT_DEPTHS_M)
            print(
                f"depths: {', '.join(f'{z:g}' for z in depths)} m (where the simulated target fits)"
            )
        unusable = [sim_rig.why_unusable(z) for z in depths]
        if len(depths) < 2 or any(unusable):
            print(f"dffd calibrate: {'; '.join(u for u in unusable if u)}", file=sys.stderr)
            return EXIT_USAGE
        # the measure the daemon would use with its default configuration
        measure = DffdConfig().estimators.focus_measure
        _load_kernels()
        procedure = calibrate_table(sim_rig, depths, measure, args.name, swept=swept)
        return _run_and_report(procedure, sim_rig, depths, swept=swept, args=args, measure=measure)
    try:
        config = load_config(args.config)
        rig = LabRig(config)
    except (ConfigError, CalibrationError) as exc:
        print(f"dffd calibrate: {exc}", file=sys.stderr)
        return EXIT_USAGE
    absent = missing_devices(config)  # as dffd run refuses them (lens.file is written here)
    if absent:
        print("dffd calibrate: " + "; ".join(absent), file=sys.stderr)
        return EXIT_USAGE
    no_terminal = terminal_problem(len(depths))  # its prompts need an operator at a terminal
    if no_terminal is not None:
        print(f"dffd calibrate: {no_terminal}", file=sys.stderr)
        return EXIT_USAGE
    if rig.optics_note is not None:
        print(f"dffd calibrate: note: {rig.optics_note}", file=sys.stderr)
    _load_kernels()
    measure = config.estimators.focus_measure
    procedure = _lab(rig, depths, measure, args.name, swept)
    return _run_and_report(procedure, rig, depths, swept=swept, args=args, measure=measure)


def output_problem(path: Path) -> str | None:
    """Why the lens table could not be written to ``path`` (``--out``), or None: checked before
    the procedure, which takes minutes."""
    target = path.resolve()  # a symlink's table is written where it points
    directory = target.parent
    if target.is_dir():
        return (
            f"--out {path} is a directory: give the lens file's path, e.g. "
            f"--out {path / 'lens.toml'}"
        )
    if not directory.is_dir():
        what = "is not a directory" if directory.exists() else "does not exist"
        return (
            f"--out {path}: {directory} {what} (calibrate does not create it): create the "
            f"directory first (mkdir -p {directory}) or give another --out"
        )
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        return (
            f"--out {path}: cannot write in {directory} ({exc.strerror or exc}): run as a user "
            "who may write there, or give another --out"
        )
    return None


def write_lens_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all: into a temporary file in the same
    directory, renamed over ``path`` (an existing file keeps its mode); OSError if it fails."""
    target = path.resolve()  # replace the file a symlink points to, not the symlink
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    created = False
    try:
        # 0o666 less the umask, as a plain write would create it
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        created = True
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        with contextlib.suppress(FileNotFoundError):
            tmp.chmod(stat.S_IMODE(target.stat().st_mode))
        tmp.replace(target)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                tmp.unlink()
        raise


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


def lens_toml(
    lens: Lens, zoom_counts: int | None, latency_frames: int, notes: list[str] | None = None
) -> str:
    """The lens calibration file (lens TOML format, as ``dffd/defaults/lenses/*.toml``);
    ``notes`` become comment lines (the fit's residuals)."""
    rows = "\n".join(
        f"    [{c}, {v:.7f}]," for c, v in zip(lens.focus_counts, lens.focus_v_mm, strict=True)
    )
    zoom = f"zoom_counts = {zoom_counts}\n" if zoom_counts is not None else ""
    f_number = f"f_number = {lens.f_number!r}\n" if lens.f_number is not None else ""
    if lens.table_sigma_v_mm > 0:  # the table's own standard error (docs/estimation.md §14)
        f_number += f"table_sigma_v_mm = {lens.table_sigma_v_mm:.3e}\n"
    if lens.table_sigma_v_at:  # and per calibrated depth (§25)
        sigma_rows = ", ".join(f"[{c}, {s:.3e}]" for c, s in lens.table_sigma_v_at)
        f_number += f"table_sigma_v_at = [{sigma_rows}]\n"
    comments = "".join(f"# {line}\n" for line in notes or [])
    response = _response_toml(lens.vertex_response) if lens.vertex_response is not None else ""
    return (
        "# Focus calibration written by `dffd calibrate` (docs/design.md §3).\n"
        f"# Measured capture latency: {latency_frames} frame(s) -> [capture] latency_frames.\n"
        f"{comments}"
        "[lens]\n"
        f'name = "{lens.name}"\n'
        f"focal_length_mm = {lens.focal_length_mm}\n"
        f"pixel_pitch_mm = {lens.pixel_pitch_mm}\n"
        f"{f_number}"
        f"{zoom}"
        f"focus_table = [\n{rows}\n]\n"
        f"{response}"
    )


def _response_toml(response: VertexResponse) -> str:
    """The ``[lens.vertex_response]`` table (docs/estimation.md §21)."""

    def floats(values: tuple[float, ...]) -> str:
        return "[" + ", ".join(f"{x:.6g}" for x in values) + "]"

    return (
        "\n# The burst fit's vertex (fitted_h) against the true offset (true_h), in half-\n"
        "# brackets, measured on the sweeps above; the estimator inverts it (estimation §21).\n"
        "[lens.vertex_response]\n"
        f'measure = "{response.measure}"\n'
        f"half_width_rel = {response.half_width_rel:.6e}\n"
        f"depth_spread_h = {response.depth_spread_h:.6g}\n"
        f"n_depths = {response.n_depths}\n"
        f"true_h = {floats(response.true_h)}\n"
        f"fitted_h = {floats(response.fitted_h)}\n"
    )


def vertex(counts: npt.NDArray[np.float64], costs: npt.NDArray[np.float64]) -> float:
    """Counts of the vertex of a parabola through the costs around their minimum."""
    i = int(np.argmin(costs))
    lo, hi = max(0, i - FIT_HALF_WIDTH), min(len(costs), i + FIT_HALF_WIDTH + 1)
    x, y = counts[lo:hi], costs[lo:hi]
    if len(x) < 3:
        return float(counts[i])
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    if a <= 0:
        return float(counts[i])
    return float(np.clip(-b / (2 * a) + x.mean(), x.min(), x.max()))


class SimRig:
    """The simulated camera in lock-step virtual time, a static target at a chosen depth."""

    def __init__(self, sim_config: Path | Any) -> None:
        """``sim_config``: a simulated-camera config file, or a loaded ``SimCameraConfig`` (the
        bench calibrates its sessions' own camera)."""
        from drivers.sim.config import load_sim_camera_config
        from drivers.sim.optics import Optics

        self.config = (
            load_sim_camera_config(sim_config) if isinstance(sim_config, Path) else sim_config
        )
        optics = Optics.from_config(self.config)
        lens = Lens.from_meta(_lens_meta(optics, self.config.zoom_counts))
        self.focal_length_mm = lens.focal_length_mm
        self.pixel_pitch_mm = lens.pixel_pitch_mm
        self.f_number: float | None = optics.f_number(self.config.zoom_counts)
        self.zoom_counts: int | None = self.config.zoom_counts
        self.focus_range = (
            int(self.config.lens.focus_far_counts),
            int(self.config.lens.focus_near_counts),
        )
        self._frame = 0  # frame index of the next render
        self._rig: Any = None  # drivers.sim.rig.SimCamera of the current target placement
        self._z_m = 3.0
        self._placed: dict[float, int] = {}  # placements so far per depth

    def radius_px(self, z_m: float) -> float:
        """The simulated target's image size r = f R / z (pixels) at ``z_m``."""
        image_mm = self.focal_length_mm * self.config.world.target.size_m / z_m
        return image_mm / self.pixel_pitch_mm

    def why_unusable(self, z_m: float) -> str | None:
        """Why the simulated target cannot be calibrated on at ``z_m`` (None: it can)."""
        limits = TrackerConfig()
        near = self.config.lens.near_focus_m
        r = self.radius_px(z_m)
        if z_m < near:
            return f"{z_m:g} m is nearer than the lens focuses ({near:g} m)"
        if r > MAX_RADIUS_FRACTION * limits.max_radius_px:
            return (
                f"at {z_m:g} m the simulated {self.config.world.target.size_m * MM_PER_M:g} mm "
                f"target is {r:.0f} px in radius, more than the tracker takes with margin "
                f"({MAX_RADIUS_FRACTION * limits.max_radius_px:.0f} px)"
            )
        if r < MIN_RADIUS_MARGIN * limits.min_radius_px:
            return f"at {z_m:g} m the simulated target is only {r:.1f} px in radius"
        return None

    def usable_depths(self, wanted: tuple[float, ...]) -> list[float]:
        """``wanted``, each depth nearer than the target fits moved out to the first usable
        multiple of :data:`DEPTH_STEP_M`, and depths where it is too small dropped."""
        limits = TrackerConfig()
        size_mm = self.config.world.target.size_m * MM_PER_M
        largest_px = MAX_RADIUS_FRACTION * limits.max_radius_px
        # r = f R / (z p) <= largest_px, and the lens focuses no nearer than near_focus_m.
        nearest = max(
            self.config.lens.near_focus_m,
            self.focal_length_mm * size_mm / (largest_px * self.pixel_pitch_mm) / MM_PER_M,
        )
        nearest = math.ceil(nearest / DEPTH_STEP_M - 1e-9) * DEPTH_STEP_M
        moved = {round(max(z, nearest), 6) for z in wanted}
        return sorted(z for z in moved if self.why_unusable(z) is None)

    async def place_target(self, z_m: float) -> None:
        """A fresh simulated session with the target at ``z_m`` (placed again: frames further
        on, new sensor noise)."""
        self._z_m = z_m
        self._rig = None
        self._placed[z_m] = self._placed.get(z_m, 0) + 1

    async def frame_at(self, counts: int, settle_frames: int) -> Image:
        """The lens is at ``counts`` well before the next exposure (virtual time: no wait)."""
        # One turn of the event loop a setting: nothing here waits, and Ctrl-C (asyncio.run
        # cancels the main task) would otherwise reach the procedure only once it had ended.
        await asyncio.sleep(0)
        source, state = self._session()
        k = self._frame
        t = source.frame_time(k)
        state.focus.jump(float(counts), t - 1.0)
        return self._render(k)

    async def step_focus(self, counts: int) -> float:
        """Move the lens at once, between the two exposures around the last delivery time."""
        source, state = self._session()
        now = source.delivery_time(self._frame - 1)
        period = 1.0 / source.fps
        exposed = (now - source.frame_time(0)) // period  # last exposure mid before now
        t_cmd = source.frame_time(int(exposed)) + 0.5 * period
        state.focus.jump(float(counts), t_cmd)
        return float(t_cmd)

    async def next_frame(self) -> tuple[Image, float]:
        """The next frame in sequence and its delivery time."""
        source, _ = self._session()
        k = self._frame
        return self._render(k), float(source.delivery_time(k))

    def _render(self, k: int) -> Image:
        source, _ = self._session()
        self._frame = k + 1
        # Render once the exposure is well over (the frames come in order: time never goes back).
        self._rig.virtual_clock.set(source.frame_time(k) + 1.0)
        image = source.render_frame(k).image
        gray: Image = image if image.ndim == 2 else image[..., 1]
        return gray

    def _session(self) -> tuple[Any, Any]:
        if self._rig is None:
            from drivers.sim.config import with_overrides
            from drivers.sim.rig import build_sim_camera

            cfg = with_overrides(
                self.config,
                {"world.trajectory": {"kind": "static", "position_m": (0.0, 0.0, self._z_m)}},
            )
            self._rig = build_sim_camera(cfg, virtual_start_s=0.0, t0=1.0)
            self._frame = SIM_REPEAT_FRAMES * (self._placed.get(self._z_m, 1) - 1)
        return self._rig.source, self._rig.state


class LabRig:
    """The real camera: VISCA on ``camera.port``, frames from ``capture.device``, an operator."""

    def __init__(
        self, config: DffdConfig, prompt: Callable[[str], Awaitable[None]] | None = None
    ) -> None:
        from drivers.visca.camera import profile_for

        if config.camera.driver != "visca" or config.capture.source not in ("v4l2", "stream"):
            raise CalibrationError(
                "the lab procedure needs camera.driver = 'visca' with camera.port, and "
                "capture.source = 'v4l2' with capture.device (or 'stream' with capture.url); "
                "use --sim for the simulator"
            )
        # lens.file's optics are reused (f is fixed at a fixed zoom); calibrate writes that file,
        # so it need not exist yet: the packaged default lens's optics then, with a note.
        self.optics_note: str | None = None
        try:
            lens = Lens.from_toml(config.lens.file)
        except LensError as exc:
            lens = Lens.from_toml(lens_table(DEFAULT_LENS))
            self.optics_note = _default_optics_note(config, lens, exc)
        self.config = config
        self.profile = profile_for(config.camera.model)
        self.focal_length_mm = lens.focal_length_mm
        self.pixel_pitch_mm = lens.pixel_pitch_mm
        self.f_number = lens.f_number
        self.zoom_counts = (
            config.lens.zoom_counts if config.lens.zoom_counts is not None else lens.zoom_counts
        )
        self.focus_range = self.profile.focus_range
        self._prompt = prompt or ask_operator
        self._camera: Any = None
        self._source: Any = None
        self._pending: asyncio.Task[None] | None = None

    async def __aenter__(self) -> LabRig:
        """Open the link and the device, initialise the camera (manual focus, the zoom)."""
        from drivers.capture import CaptureSettings, OpenCVFrameSource
        from drivers.visca.camera import Camera
        from drivers.visca.link import ViscaLink

        cfg = self.config
        assert cfg.camera.port is not None  # validated with driver = 'visca'
        self._link = ViscaLink(cfg.camera.port, cfg.camera.baudrate)
        await self._link.__aenter__()
        self._camera = Camera(self._link, cfg.camera.address, self.profile)
        async with asyncio.timeout(CAMERA_INIT_TIMEOUT_S):
            await self._camera.initialize()
            if self.zoom_counts is not None:
                await self._camera.zoom_direct(self.zoom_counts)
        # latency_s = 0: frame.t is the delivery (read) time, the clock of step_focus.
        if cfg.capture.source == "stream":
            from drivers.stream import StreamFrameSource, StreamSettings

            assert cfg.capture.url is not None  # validated with source = 'stream'
            self._source = StreamFrameSource(
                StreamSettings(cfg.capture.url, fps=cfg.capture.fps, timestamps="arrival")
            )
        else:
            assert cfg.capture.device is not None  # validated with source = 'v4l2'
            settings = CaptureSettings(
                device=cfg.capture.device, width=cfg.capture.width, height=cfg.capture.height,
                fps=cfg.capture.fps, fourcc=cfg.capture.fourcc, latency_s=0.0,
            )  # fmt: skip
            self._source = OpenCVFrameSource(settings)
        await self._source.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        """Close the device and the link."""
        if self._pending is not None:
            self._pending.cancel()
        if self._source is not None:
            await self._source.close()
        await self._link.__aexit__(None, None, None)

    async def place_target(self, z_m: float) -> None:
        """Ask the operator to place the target and wait for Enter (InputEndedError: Ctrl-D)."""
        await self._prompt(
            f"Place the target {z_m:g} m from the camera on the optical axis, then press Enter: "
        )

    async def frame_at(self, counts: int, settle_frames: int) -> Image:
        """Focus Direct, wait for Completion, skip the frames that may predate it."""
        await self._finish_pending()
        await self._camera.focus_direct(counts)
        done = time.monotonic()
        wait = settle_frames / self.config.capture.fps
        while True:
            image, delivered = await self.next_frame()
            if delivered >= done + wait:
                return image

    async def step_focus(self, counts: int) -> float:
        """Write Focus Direct now; its Completion is awaited before the next move."""
        await self._finish_pending()
        handle = await self._camera.start_focus_direct(counts)
        t = time.monotonic()
        self._pending = asyncio.ensure_future(_completion(handle))
        return t

    async def next_frame(self) -> tuple[Image, float]:
        """The next frame from the device (gray) and its read time."""
        async with asyncio.timeout(FRAME_TIMEOUT_S):
            frame = await self._source.next_frame()
        image: Image = frame.image if frame.image.ndim == 2 else frame.image[..., 1]
        return image, float(frame.t)

    async def _finish_pending(self) -> None:
        if self._pending is not None:
            task, self._pending = self._pending, None
            await task


# -- private helpers --------------------------------------------------------------------------
def _run_and_report(
    procedure: Coroutine[Any, Any, CalibrationResult],
    rig: Rig,
    depths: list[float],
    *,
    swept: list[DepthPoint],
    args: argparse.Namespace,
    measure: FocusMeasure,
) -> int:
    """Run the procedure, then print and write its table. Stopped by the operator (Ctrl-C;
    Ctrl-D at a prompt): what had been measured (``swept``), and nothing written."""
    # The table is written only after asyncio.run returned it: a Ctrl-C during the final fit
    # (seconds; nothing awaits there) ends the main task cancelled, and nothing was written.
    try:
        result = asyncio.run(procedure)
    except CalibrationError as exc:
        print(f"dffd calibrate: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except InputEndedError:
        why = "the input ended at the prompt (Ctrl-D)"
    except KeyboardInterrupt:
        why = "interrupted (Ctrl-C)"
    else:
        return _report(result, rig, args, measure)
    stopped = stopped_message(why, depths, len(swept), args.out)
    print(f"\ndffd calibrate: {stopped}", file=sys.stderr)
    return EXIT_INTERRUPTED


def _report(
    result: CalibrationResult, rig: Rig, args: argparse.Namespace, measure: FocusMeasure
) -> int:
    """Print the table's residuals and the latency; write the lens file (``--out``) or print it."""
    lines = result.lines()
    latency = result.latency_frames
    print(f"focus measure: {measure} ([estimators] focus_measure)")
    print("\n".join(lines))
    print(f"capture latency: {latency} frame(s) in flight")
    notes = [f"Focus measure: {measure}.", *lines]
    text = lens_toml(result.table.lens, rig.zoom_counts, latency, notes)
    if args.out is None:
        print(text)
        return EXIT_OK
    try:
        write_lens_file(args.out, text)
    except OSError as exc:
        print(text)  # the calibration is not lost
        print(
            f"dffd calibrate: cannot write the lens table to --out {args.out}: {exc}; it is "
            "printed on stdout above: save it as a lens file yourself (from [lens] on)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    print(f"lens table written to {args.out}")
    return EXIT_OK


async def _lab(
    rig: LabRig, depths: list[float], measure: FocusMeasure, name: str, swept: list[DepthPoint]
) -> CalibrationResult:
    from drivers.frames import FrameSourceError
    from drivers.visca.errors import ViscaError

    try:
        async with rig:
            return await calibrate_table(rig, depths, measure, name, swept=swept)
    except (ViscaError, FrameSourceError, TimeoutError, OSError) as exc:
        raise CalibrationError(
            f"camera or video device failed: {exc}; check camera.port, capture.device, the "
            "cables and that the camera is powered"
        ) from exc


def _load_kernels() -> None:
    """Load the tracker's compiled kernels (compile them on a first start, saying so): the
    procedure's results must not depend on timing, so no NumPy twins meanwhile."""
    say_if_compiling("calibrate")
    kernel_dispatch.use_compiled()


def _default_optics_note(config: DffdConfig, lens: Lens, exc: LensError) -> str:
    """What the lab procedure starts from when ``lens.file`` cannot be read."""
    file = config.lens.file
    why = (
        f"lens.file {file} does not exist yet (this calibration writes its table)"
        if not file.exists()
        else f"lens.file: {exc}"
    )
    optics = f"focal_length_mm {lens.focal_length_mm:g}, pixel_pitch_mm {lens.pixel_pitch_mm:g}"
    if lens.f_number is not None:
        optics += f", f_number {lens.f_number:g}"
    if config.lens.zoom_counts is None and lens.zoom_counts is not None:
        optics += f", zoom_counts {lens.zoom_counts}"
    return (
        f"{why}; using the optics of the packaged lens {lens.name}: {optics}. The table "
        "written carries them: check them against your camera (f at the zoom used) and grabber; "
        "to start from others, name a lens file with them for this run (DFFD_LENS__FILE=FILE)"
    )


def _blocks(image: Image) -> npt.NDArray[np.float64]:
    """Means of CHANGE_BLOCK_PX² blocks (the image cropped to whole blocks)."""
    b = CHANGE_BLOCK_PX
    h, w = image.shape[0] // b * b, image.shape[1] // b * b
    cropped = image[:h, :w].astype(np.float64)
    means: npt.NDArray[np.float64] = cropped.reshape(h // b, b, w // b, b).mean(axis=(1, 3))
    return means


async def _completion(handle: Any) -> None:
    await handle.completed()


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


def _lens_meta(optics: object, zoom_counts: int) -> dict[str, object]:
    import tomllib

    text = optics.lens_table_toml(zoom_counts)  # type: ignore[attr-defined]
    data = tomllib.loads(text)["lens"]
    return {k: data[k] for k in ("name", "focal_length_mm", "pixel_pitch_mm", "focus_table")}


__all__ = [
    "CalibrationResult",
    "LabRig",
    "Rig",
    "SimRig",
    "calibrate",
    "calibrate_table",
    "lens_toml",
    "measure_latency",
    "output_problem",
    "run",
    "sharpest",
    "vertex",
    "write_lens_file",
]
