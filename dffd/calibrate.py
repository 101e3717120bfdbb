"""``dffd calibrate``: fit the focus counts ↔ v table; the capture latency (design.md §3, §5).

One procedure (:func:`dffd.calibrate_procedure.calibrate_table`: the capture latency, a focus
sweep per depth, the table fitted and checked) runs against a rig (:mod:`dffd.calibrate_rigs`) —
the simulated camera (``--sim``: :class:`~dffd.calibrate_rigs.SimRig`, lock-step virtual time)
or the real camera (:class:`~dffd.calibrate_rigs.LabRig`: the VISCA camera on ``camera.port``
and the video device ``capture.device`` of ``--config``). Only the rig differs; the sweep, the
fit and the file written are the same code. This module is the command: its arguments checked
before anything starts, the procedure run, the table printed and written
(:mod:`dffd.calibrate_lensfile`). What the procedure measures and fits:
:mod:`dffd.calibrate_procedure`.

Capture latency in seconds for network video: ``dffd calibrate --latency --config FILE``
(:mod:`dffd.latency`).

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
import sys
from collections.abc import Coroutine
from typing import Any

from dffd.calibrate_lensfile import lens_toml, write_lens_file
from dffd.calibrate_operator import InputEndedError, stopped_message, terminal_problem
from dffd.calibrate_procedure import CalibrationResult, Rig, calibrate_table
from dffd.calibrate_rigs import LabRig, SimRig
from dffd.calibrate_types import CalibrationError, DepthPoint
from dffd.cli.loading import say_if_compiling
from dffd.cli.output_path import output_problem
from dffd.config import ConfigError, DffdConfig, load_config, missing_devices
from dffd.core import kernel_dispatch
from dffd.exitcodes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from dffd.literals import FocusMeasure
from drivers.sim.resources import reference_camera_file

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
    if args.out is not None:
        unwritable = output_problem(
            args.out, option="--out", command="calibrate", what="lens file", example="lens.toml"
        )
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


__all__ = ["run"]
