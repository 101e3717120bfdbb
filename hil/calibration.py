"""The bench calibrates its lens table as the lab does (issue 11.7).

Before a scenario's sessions run, the focus table the estimator is told is fitted by the code of
``dffd calibrate --sim`` (:func:`dffd.calibrate.calibrate` on a :class:`dffd.calibrate.SimRig`
of the session's own simulated camera: optics, lens, sensor noise and target), once per optics
model and seed, cached under the run directory. The bench then scores on that table, and
``report.json`` reports the calibration's own error against the simulator's true focus curve
(``calibration`` block): the depth a calibrated setting stands for against the depth that
setting truly focuses, over the working range.
"""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dffd.calibrate import SimRig, calibrate, lens_from_points, lens_toml
from dffd.core.lens import Lens
from hil.scenario import Scenario
from hil.simbuild import sim_camera_config, truth_lens_table

logger = logging.getLogger(__name__)

# Target depths of the calibration sweeps (m): the bench's working range (1.5–12 m) with the
# lab procedure's spacing (docs/design.md, dffd calibrate), plus one beyond it so that the
# table's far end is measured, not extrapolated.
CALIBRATION_DEPTHS_M = (1.5, 2.0, 3.0, 4.5, 7.0, 10.0, 14.0)
# Depths (m) at which the calibrated table is scored against the true focus curve.
SCORE_DEPTHS_M = tuple(float(z) for z in np.geomspace(1.5, 12.0, 25))


@dataclass(frozen=True, slots=True)
class Calibration:
    """A fitted lens table and its error against the simulator's true focus curve."""

    lens_path: Path
    report: dict[str, Any]


def calibrated_lens(scenario: Scenario, seed: int, cache_dir: Path) -> Calibration:
    """The table ``dffd calibrate --sim`` fits on this scenario's camera with ``seed`` (cached
    in ``cache_dir`` as ``<optics>-s<seed>.toml`` and ``.json``)."""
    _case, trajectory = scenario.expand()[0]
    config, _ = sim_camera_config(scenario, trajectory, seed)
    name = f"{config.optics.model}-s{seed}"
    toml_path, json_path = cache_dir / f"{name}.toml", cache_dir / f"{name}.json"
    if toml_path.exists() and json_path.exists():
        return Calibration(toml_path, json.loads(json_path.read_text("utf-8")))
    cache_dir.mkdir(parents=True, exist_ok=True)
    rig = SimRig(config)
    points, latency = asyncio.run(calibrate(rig, list(CALIBRATION_DEPTHS_M)))
    lens = lens_from_points(f"calibrated-{name}", rig.focal_length_mm, rig.pixel_pitch_mm, points)
    toml_path.write_text(lens_toml(lens, rig.zoom_counts, latency), "utf-8")
    truth = Lens.from_toml(truth_lens_table(config))
    report = calibration_error(lens, truth) | {
        "optics": config.optics.model,
        "seed": seed,
        "depths_m": list(CALIBRATION_DEPTHS_M),
        "latency_frames": latency,
        "table": str(toml_path),
    }
    json_path.write_text(json.dumps(report, indent=2) + "\n", "utf-8")
    logger.info("calibrated %s: depth error rms %.4f m", name, report["depth_err_rms_m"])
    return Calibration(toml_path, report)


def calibration_error(calibrated: Lens, truth: Lens) -> dict[str, Any]:
    """Error of a calibrated table: at each scoring depth z, the setting that truly focuses z
    is read back through the calibrated table (the depth a perfect vertex would give)."""
    errs, rel, dv = [], [], []
    for z in SCORE_DEPTHS_M:
        counts = truth.counts_for_depth(z)
        v_true = truth.v_from_counts(counts)
        v_cal = calibrated.v_from_counts(counts)
        z_cal = calibrated.depth_from_v(v_cal)
        z_true = truth.depth_from_v(v_true)
        errs.append(z_cal - z_true)
        rel.append((z_cal - z_true) / z_true)
        dv.append((v_cal - v_true) * 1e3)
    e, r, d = np.asarray(errs), np.asarray(rel), np.asarray(dv)
    return {
        "score_depths_m": [SCORE_DEPTHS_M[0], SCORE_DEPTHS_M[-1]],
        "depth_err_rms_m": float(np.sqrt(np.mean(e * e))),
        "depth_err_max_abs_m": float(np.abs(e).max()),
        "depth_err_rel_rms": float(np.sqrt(np.mean(r * r))),
        "v_err_rms_um": float(np.sqrt(np.mean(d * d))),
        "v_err_max_abs_um": float(np.abs(d).max()),
        "per_depth": [
            {"z_m": z, "depth_err_m": float(x), "v_err_um": float(y)}
            for z, x, y in zip(SCORE_DEPTHS_M, e, d, strict=True)
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
