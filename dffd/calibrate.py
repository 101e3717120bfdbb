"""``dffd calibrate``: fit the focus counts ↔ v table, measure the capture latency (DESIGN §2, §4).

Focus table. The target is placed at several known depths z; at each, the focus is swept (coarse
over the whole range, then fine around the sharpest setting), each frame's focus cost (2) is
taken exactly as the core takes it (active contour normals → :func:`dffd.core.focus.focus_cost`),
and the sharpest counts is the vertex of a parabola fitted to the costs around the minimum. The
thin lens gives the lens-to-sensor distance of that depth, ``v = f z / (z − f)``; the pairs
(counts, v), sorted and checked monotone, are written as a lens TOML file (PCHIP-interpolated by
:class:`dffd.core.lens.Lens`).

Capture latency. A focus step is commanded between two exposures and frames are counted until
the image changes; the frames delivered in between are the frames in flight.

``--sim`` runs both against the simulated camera in lock-step virtual time (its optics are
written independently of the estimator, so this is a genuine test of the procedure). The lab
procedure on real hardware (serial port + video device, an operator placing the target at each
depth) is not implemented yet: the command says so and exits 2.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from dffd.config import REPO_ROOT
from dffd.core.contour import ContourTracker, TrackerConfig, find_target
from dffd.core.focus import focus_cost
from dffd.core.lens import MM_PER_M, Lens

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2

DEFAULT_DEPTHS_M = (1.0, 1.5, 2.0, 3.0, 4.5, 7.0, 10.0, 20.0)
DEFAULT_SIM_CAMERA_FILE = REPO_ROOT / "config" / "sim-camera.toml"
COARSE_POINTS = 33  # focus settings of the coarse sweep over the whole range
FINE_POINTS = 17  # … of the fine sweep around the coarse minimum (± two coarse steps)
FIT_HALF_WIDTH = 3  # points either side of the minimum used for the vertex fit
# Mean absolute grey-level change that counts as "the image changed" after a focus step.
CHANGE_THRESHOLD_DN = 0.5
LATENCY_MAX_FRAMES = 20  # give up counting after this many frames


class CalibrationError(RuntimeError):
    """The sweep could not find a sharp setting (target not found, flat cost, …)."""


@dataclass(frozen=True, slots=True)
class DepthPoint:
    """The sharpest focus setting found for one known depth."""

    z_m: float
    counts: int
    v_mm: float
    cost_min: float


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``dffd calibrate`` options."""
    parser.add_argument("--sim", action="store_true", help="calibrate the simulated camera")
    parser.add_argument(
        "--sim-config", type=Path, default=DEFAULT_SIM_CAMERA_FILE, metavar="FILE",
        help="simulated-camera TOML (default config/sim-camera.toml)",
    )  # fmt: skip
    parser.add_argument(
        "--depths", default=",".join(str(z) for z in DEFAULT_DEPTHS_M), metavar="Z1,Z2,…",
        help="known target depths in metres",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, metavar="FILE", help="write the lens TOML here")
    parser.add_argument("--name", default="calibrated", help="lens name in the TOML file")


def run(args: argparse.Namespace) -> int:
    """Calibrate; print the table and the latency; return the exit code."""
    if not args.sim:
        print(
            "dffd calibrate: only --sim is implemented; the lab procedure on a real camera "
            "(serial port + video device, target at known depths) is still to be written",
            file=sys.stderr,
        )
        return EXIT_USAGE
    try:
        depths = sorted({float(z) for z in args.depths.split(",") if z.strip()})
    except ValueError:
        print(f"dffd calibrate: --depths {args.depths!r} is not a list of numbers", file=sys.stderr)
        return EXIT_USAGE
    if len(depths) < 2 or min(depths) <= 0:
        print("dffd calibrate: give at least two positive depths", file=sys.stderr)
        return EXIT_USAGE
    rig = SimRig(args.sim_config)
    try:
        points = [rig.sharpest(z) for z in depths]
        lens = lens_from_points(args.name, rig.focal_length_mm, rig.pixel_pitch_mm, points)
        latency = rig.latency_frames()
    except CalibrationError as exc:
        print(f"dffd calibrate: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    for p in points:
        print(f"z = {p.z_m:6.2f} m  sharpest counts {p.counts:6d}  v = {p.v_mm:.6f} mm")
    print(f"capture latency: {latency} frame(s) in flight")
    text = lens_toml(lens, rig.zoom_counts, latency)
    if args.out is not None:
        args.out.write_text(text, encoding="utf-8")
        print(f"lens table written to {args.out}")
    else:
        print(text)
    return EXIT_OK


def lens_from_points(
    name: str, focal_length_mm: float, pixel_pitch_mm: float, points: list[DepthPoint]
) -> Lens:
    """A :class:`Lens` from the sweep results; raises CalibrationError if not monotone."""
    pts = sorted(points, key=lambda p: p.counts)
    counts = [p.counts for p in pts]
    v = [p.v_mm for p in pts]
    steps = [b - a for a, b in itertools.pairwise(v)]
    monotone = all(d > 0 for d in steps) or all(d < 0 for d in steps)
    if len(set(counts)) != len(counts) or not monotone:
        raise CalibrationError(
            "the sharpest settings are not monotone in depth "
            f"(counts {counts}, v {[round(x, 4) for x in v]}); use depths further apart"
        )
    return Lens(name, focal_length_mm, pixel_pitch_mm, tuple(counts), tuple(v))


def lens_toml(lens: Lens, zoom_counts: int | None, latency_frames: int) -> str:
    """The lens calibration file (``config/lenses/*.toml`` format)."""
    rows = "\n".join(
        f"    [{c}, {v:.6f}]," for c, v in zip(lens.focus_counts, lens.focus_v_mm, strict=True)
    )
    zoom = f"zoom_counts = {zoom_counts}\n" if zoom_counts is not None else ""
    return (
        "# Focus calibration written by `dffd calibrate` (DESIGN §2).\n"
        f"# Measured capture latency: {latency_frames} frame(s) -> [capture] latency_frames.\n"
        "[lens]\n"
        f'name = "{lens.name}"\n'
        f"focal_length_mm = {lens.focal_length_mm}\n"
        f"pixel_pitch_mm = {lens.pixel_pitch_mm}\n"
        f"{zoom}"
        f"focus_table = [\n{rows}\n]\n"
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
    """The simulated camera in lock-step time, a static target at a chosen depth."""

    def __init__(self, sim_config: Path) -> None:
        from drivers.sim.config import load_sim_camera_config
        from drivers.sim.optics import Optics

        self.config = load_sim_camera_config(sim_config)
        optics = Optics.from_config(self.config)
        lens = Lens.from_meta(_lens_meta(optics, self.config.zoom_counts))
        self.focal_length_mm = lens.focal_length_mm
        self.pixel_pitch_mm = lens.pixel_pitch_mm
        self.zoom_counts = self.config.zoom_counts
        self.focus_range = (
            int(self.config.lens.focus_far_counts),
            int(self.config.lens.focus_near_counts),
        )
        self._frame = 0  # frame index of the next sweep render (one per setting)
        self._clock = _Clock()

    def sharpest(self, z_m: float) -> DepthPoint:
        """Sweep the focus with the target at ``z_m``; the sharpest counts and its v."""
        source, state = self._session(z_m)
        lo, hi = self.focus_range
        coarse = np.linspace(lo, hi, COARSE_POINTS)
        costs = self._costs(source, state, coarse)
        best = float(coarse[int(np.nanargmin(costs))])
        step = (hi - lo) / (COARSE_POINTS - 1)
        fine = np.linspace(max(lo, best - 2 * step), min(hi, best + 2 * step), FINE_POINTS)
        fine_costs = self._costs(source, state, fine)
        ok = np.isfinite(fine_costs)
        if ok.sum() < 3:
            raise CalibrationError(f"target not measurable at {z_m} m; check the scene")
        counts = round(vertex(fine[ok], fine_costs[ok]))
        f = self.focal_length_mm
        z = z_m * MM_PER_M
        return DepthPoint(z_m, counts, f * z / (z - f), float(np.nanmin(fine_costs)))

    def latency_frames(self) -> int:
        """Frames delivered after a focus step before one shows it (the frames in flight)."""
        source, state = self._session(3.0)
        lo, hi = self.focus_range
        fps = source.fps
        k0 = 10
        state.focus.jump(lo + (hi - lo) // 2, source.frame_time(0) - 1.0)
        t_cmd = source.frame_time(k0) + 0.5 / fps  # between two exposures
        state.focus.jump(lo, t_cmd)
        prev = source.render_frame(k0).image.astype(np.float64)
        k = k0 + 1
        while k < k0 + LATENCY_MAX_FRAMES:
            if source.delivery_time(k) < t_cmd:
                prev = source.render_frame(k).image.astype(np.float64)
                k += 1
                continue
            image = source.render_frame(k).image.astype(np.float64)
            if float(np.abs(image - prev).mean()) > CHANGE_THRESHOLD_DN:
                # Frames delivered after the command whose image had not changed yet.
                in_flight = sum(1 for j in range(k0, k) if source.delivery_time(j) >= t_cmd)
                return in_flight
            prev = image
            k += 1
        raise CalibrationError("the image never changed after a focus step")

    def _session(self, z_m: float):  # type: ignore[no-untyped-def]
        from drivers.sim.config import with_overrides
        from drivers.sim.source import SimFrameSource, camera_state_for

        cfg = with_overrides(
            self.config,
            {"world.trajectory": {"kind": "static", "position_m": (0.0, 0.0, z_m)}},
        )
        clock = _Clock()
        state = camera_state_for(cfg, clock=clock)
        source = SimFrameSource.from_config(cfg, state, t0=1.0)
        self._clock = clock
        return source, state

    def _costs(self, source, state, settings: npt.NDArray[np.float64]):  # type: ignore[no-untyped-def]
        out = np.full(len(settings), np.nan)
        tracker = ContourTracker(TrackerConfig())
        for i, c in enumerate(settings):
            k = self._frame
            self._frame += 1
            t = source.frame_time(k)
            state.focus.jump(float(c), t - 1.0)
            self._clock.t = t + 1.0
            frame = source.render_frame(k)
            gray = frame.image if frame.image.ndim == 2 else frame.image[..., 1]
            poly = find_target(gray)
            if poly is None or not tracker.start(gray, poly, frame.t):
                continue
            obs = tracker.update(gray, frame.t, "translation")
            cost = focus_cost(obs.peak_sq)
            if cost is not None:
                out[i] = cost[0]
        return out


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _lens_meta(optics: object, zoom_counts: int) -> dict[str, object]:
    import tomllib

    text = optics.lens_table_toml(zoom_counts)  # type: ignore[attr-defined]
    data = tomllib.loads(text)["lens"]
    return {k: data[k] for k in ("name", "focal_length_mm", "pixel_pitch_mm", "focus_table")}


__all__ = [
    "CalibrationError",
    "DepthPoint",
    "SimRig",
    "configure_parser",
    "lens_from_points",
    "lens_toml",
    "run",
    "vertex",
]
