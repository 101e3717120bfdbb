"""The bench calibrates its lens table as the lab does (issue 11.7).

Before a scenario's sessions run, the focus table the estimator is told is fitted by the code of
``dffd calibrate --sim`` (:func:`dffd.calibrate_procedure.calibrate` and
:func:`dffd.calibrate_fit.fit_table` on a :class:`dffd.calibrate_rigs.SimRig` of the session's
own simulated camera: optics, lens, sensor noise and target; the lab's default depths; the
estimator's focus measure), once per optics model and seed, cached under the run directory (the
file name carries a key of the camera, the measure and the procedure, so a changed camera or
procedure is calibrated anew). The bench then scores on that table, and ``report.json`` reports
the calibration's own error against the simulator's true focus curve (``calibration`` block):
the depth a calibrated setting stands for against the depth that setting truly focuses, over the
working range; and the fit's residuals.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dffd.calibrate import DEFAULT_DEPTHS_M
from dffd.calibrate_check import REPEAT_SIGMA, TableCheck
from dffd.calibrate_fit import VERTEX_WINDOW_BLUR_PX
from dffd.calibrate_lensfile import lens_toml
from dffd.calibrate_procedure import FRAMES_PER_SETTING, calibrate_table
from dffd.calibrate_rigs import SimRig
from dffd.core.lens import Lens, VertexResponse
from dffd.literals import FocusMeasure
from hil.scenario import Scenario
from hil.simbuild import sim_camera_config, truth_lens_table

logger = logging.getLogger(__name__)

# Bump when the procedure changes what it writes: cached tables of another version are refitted.
# 8: the closed loop's bracket ends; 9: the axis switch (estimation §16); 10: the vertex response;
# 11: the table's σ per calibrated depth (estimation §25)
PROCEDURE_VERSION = 11
# Depths (m) at which the calibrated table is scored against the true focus curve.
SCORE_DEPTHS_M = tuple(float(z) for z in np.geomspace(1.5, 12.0, 25))


@dataclass(frozen=True, slots=True)
class Calibration:
    """A fitted lens table and its error against the simulator's true focus curve."""

    lens_path: Path
    report: dict[str, Any]


def calibrated_lens(
    scenario: Scenario, seed: int, cache_dir: Path, depths_m: tuple[float, ...] | None = None
) -> Calibration:
    """The table ``dffd calibrate --sim`` fits on this scenario's camera with ``seed`` (cached
    in ``cache_dir`` as ``<optics>-s<seed>.toml`` and ``.json``)."""
    _case, trajectory = scenario.expand()[0]
    config, _ = sim_camera_config(scenario, trajectory, seed)
    measure = _focus_measure(scenario)
    name = f"{config.optics.model}-s{seed}"
    wanted = DEFAULT_DEPTHS_M if depths_m is None else depths_m
    key = _cache_key(config, measure, wanted)
    toml_path, json_path = cache_dir / f"{name}-{key}.toml", cache_dir / f"{name}-{key}.json"
    if toml_path.exists() and json_path.exists():
        return Calibration(toml_path, json.loads(json_path.read_text("utf-8")))
    cache_dir.mkdir(parents=True, exist_ok=True)
    rig = SimRig(config)
    depths = rig.usable_depths(wanted)
    started = time.monotonic()
    result = asyncio.run(calibrate_table(rig, depths, measure, f"calibrated-{name}"))
    table, latency, check = result.table, result.latency_frames, result.check
    wall_s = time.monotonic() - started
    lines = result.lines()
    toml_path.write_text(lens_toml(table.lens, rig.zoom_counts, latency, lines), "utf-8")
    truth = Lens.from_toml(truth_lens_table(config))
    fit = table.fit
    report = calibration_error(table.lens, truth, check) | {
        "optics": config.optics.model,
        "seed": seed,
        "focus_measure": measure,
        "depths_m": depths,
        "frames_per_setting": FRAMES_PER_SETTING,
        "vertex_window_blur_px": VERTEX_WINDOW_BLUR_PX,
        "latency_frames": latency,
        "wall_s": round(wall_s, 1),
        "fit": None
        if fit is None
        else {
            "degree": fit.model.degree,
            "spline": fit.model.spline is not None,
            "residual_v_rms_um": fit.rms_v_um,
            "residual_depth_rms_mm": fit.rms_depth_mm,
            "loo_v_rms_um": fit.loo_rms_v_um,
            "rejected_depths_m": sorted(
                {p.placed_m for p, ok in zip(table.model_points, fit.used, strict=True) if not ok}
            ),
            "spline_lambda": None if math.isnan(fit.model.spline_lam) else fit.model.spline_lam,
            # the refit passes' v axis (the polynomial, or the whole model after the switch)
            # and the polynomial axis's misfit to its own bracket ends that chose it (σ rms)
            "axis": table.axis,
            "axis_misfit_sigma": None
            if math.isnan(table.axis_misfit_sigma)
            else round(table.axis_misfit_sigma, 2),
            # how each depth's sweep was read (closed loop, pinned at the focus range's end, …)
            "vertex_rules": {f"{p.z_m:g}": p.rule for p in table.points},
        },
        "check": None if check is None else _check_report(check),
        "vertex_response": _response_report(table.lens.vertex_response),
        "repeated_depths_m": list(result.repeated),
        "sweeps": len(result.points),
        "table": str(toml_path),
    }
    json_path.write_text(json.dumps(report, indent=2) + "\n", "utf-8")
    logger.info("calibrated %s: depth error rms %.4f m", name, report["depth_err_rms_m"])
    return Calibration(toml_path, report)


def _focus_measure(scenario: Scenario) -> FocusMeasure:
    """The focus measure the scenario's estimator uses (the calibration must use the same)."""
    from hil.lockstep import daemon_config, pipeline_config

    return pipeline_config(scenario, daemon_config()).focus_measure


def _cache_key(config: Any, measure: str, depths: tuple[float, ...]) -> str:
    """Eight hex digits of the camera (without its trajectory), the measure and the procedure."""
    camera = config.model_dump(mode="json")
    camera.get("world", {}).pop("trajectory", None)
    text = json.dumps([camera, measure, PROCEDURE_VERSION, depths], sort_keys=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:8]


def calibration_error(
    calibrated: Lens, truth: Lens, check: TableCheck | None = None
) -> dict[str, Any]:
    """Error of a calibrated table: at each scoring depth z, the setting that truly focuses z
    is read back through the calibrated table (the depth a perfect vertex would give); with the
    table's ``check``, that error against the table's own σ there."""
    errs, rel, dv, sig = [], [], [], []
    for z in SCORE_DEPTHS_M:
        counts = truth.counts_for_depth(z)
        v_true = truth.v_from_counts(counts)
        v_cal = calibrated.v_from_counts(counts)
        z_cal = calibrated.depth_from_v(v_cal)
        z_true = truth.depth_from_v(v_true)
        errs.append(z_cal - z_true)
        rel.append((z_cal - z_true) / z_true)
        dv.append((v_cal - v_true) * 1e3)
        sig.append(math.nan if check is None else check.sigma_v_um_at(counts))
    e, r, d, s = np.asarray(errs), np.asarray(rel), np.asarray(dv), np.asarray(sig)
    own = {}
    if check is not None:
        ratio = np.abs(d) / s
        own = {
            # the table's error in units of its own σ: ~1 when the σ is honest
            "v_err_over_sigma_rms": float(np.sqrt(np.mean(ratio**2))),
            "within_2_sigma": float(np.mean(ratio <= 2.0)),
        }
    return own | {
        "score_depths_m": [SCORE_DEPTHS_M[0], SCORE_DEPTHS_M[-1]],
        "depth_err_rms_m": float(np.sqrt(np.mean(e * e))),
        "depth_err_max_abs_m": float(np.abs(e).max()),
        "depth_err_rel_rms": float(np.sqrt(np.mean(r * r))),
        "v_err_rms_um": float(np.sqrt(np.mean(d * d))),
        "v_err_max_abs_um": float(np.abs(d).max()),
        "per_depth": [
            {"z_m": z, "depth_err_m": float(x), "v_err_um": float(y), "sigma_v_um": float(q)}
            for z, x, y, q in zip(SCORE_DEPTHS_M, e, d, s, strict=True)
        ],
    }


def _response_report(response: VertexResponse | None) -> dict[str, Any] | None:
    """The vertex response the table carries (docs/estimation.md §21): its slopes near the
    centre and across the bracket, the spread between the sweeps."""
    if response is None:
        return None
    t, f = np.asarray(response.true_h), np.asarray(response.fitted_h)

    def slope(reach: float) -> float:
        sel = np.abs(t) <= reach + 1e-9
        return round(float(np.polyfit(t[sel], f[sel], 1)[0]), 4)

    return {
        "measure": response.measure,
        "sweeps": response.n_depths,
        "offsets_h": [t[0], t[-1]],
        "slope_within_0.3h": slope(0.3),
        "slope_within_0.9h": slope(0.9),
        "spread_between_sweeps_h": response.depth_spread_h,
    }


def _check_report(check: TableCheck) -> dict[str, Any]:
    """The table's own uncertainty per calibrated depth (report.json's calibration block)."""
    return {
        "repeat_sigma": REPEAT_SIGMA,
        "misfit_scale": check.misfit_scale,
        "loo_z_rms": float(np.sqrt(np.nanmean([d.z_score**2 for d in check.depths]))),
        "sigma_depth_mm_max": max(d.sigma_depth_mm for d in check.depths),
        "per_depth": [
            {
                "z_m": d.z_m,
                "sigma_v_um": d.sigma_v_um,
                "sigma_depth_mm": d.sigma_depth_mm,
                # None: a depth not in the fit (its bracket meets the end of the focus range)
                "loo_v_um": d.loo_v_um if math.isfinite(d.loo_v_um) else None,
                "z_score": d.z_score if math.isfinite(d.z_score) else None,
                "sweeps": d.n_sweeps,
            }
            for d in check.depths
        ],
    }


def pooled_report(calibrations: list[Calibration]) -> dict[str, Any] | None:
    """The ``calibration`` block of report.json: each (optics, seed) table's error."""
    if not calibrations:
        return None
    rows = [{k: v for k, v in c.report.items() if k != "per_depth"} for c in calibrations]
    return {
        "method": "dffd calibrate --sim on the session's camera (hil/calibration.py)",
        "tables": rows,
        "depth_err_rms_m_max": max(r["depth_err_rms_m"] for r in rows),
    }
