"""Payload conversion: the core's outputs → the MQTT payload models (``dffd.mqtt.models``).

Non-finite numbers become null, negative sizes and σ are dropped, and every payload is
numbered per kind. An output that does not fit its schema is skipped and counted, never fatal.

The first-depth gate (:class:`dffd.first_depth.FirstDepthGate`) lives in the shared core step
(:mod:`dffd.step`), so the daemon publishes what the bench scores and ``dffd replay`` writes; it
is re-exported here. :func:`without_depth` nulls a held-back estimate's depth fields.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from dffd.core.pipeline import Estimate as CoreEstimate
from dffd.core.pipeline import Measurement as CoreMeasurement
from dffd.core.tracking3d_types import Track3DEstimate
from dffd.first_depth import (
    FIRST_DEPTH_FORCE_BURSTS,
    FIRST_DEPTH_MAX_BURSTS,
    FIRST_DEPTH_MAX_REL_SIGMA,
    FirstDepthGate,
)
from dffd.mqtt import models

_LOGGER = logging.getLogger(__name__)

_M = TypeVar("_M", bound=BaseModel)
_T = TypeVar("_T")

__all__ = [
    "FIRST_DEPTH_FORCE_BURSTS",
    "FIRST_DEPTH_MAX_BURSTS",
    "FIRST_DEPTH_MAX_REL_SIGMA",
    "FirstDepthGate",
    "Payloads",
    "nonneg",
    "truth_payload",
    "without_depth",
]


class Payloads:
    """Numbers and converts the core's outputs; counts the ones that do not fit the schemas."""

    def __init__(self, default_best: models.EstimatorName) -> None:
        self.default_best = default_best  # ``best`` when the core names no known estimator
        self.estimate_seq = 0
        self.measurement_seq = 0
        self.skipped = 0  # outputs that did not fit their schema

    def estimate(
        self, est: CoreEstimate, track: Track3DEstimate | None = None
    ) -> models.Estimate | None:
        """The ``…/estimate`` payload of ``est`` and the frame's 3D ``track`` (None: skipped)."""
        return self.or_none(self._estimate, (est, track))

    def measurement(self, m: CoreMeasurement) -> models.Measurement | None:
        """The ``…/measurement`` payload of a burst (None: skipped)."""
        return self.or_none(self._measurement, m)

    def or_none(self, build: Callable[[_T], _M], item: _T) -> _M | None:
        """A payload, or None (logged, counted) when the core's output does not fit the schema.

        One odd result must never stop the service: e.g. the core reports a burst cut short by
        a link fault with fewer than the three frames the ``…/measurement`` schema requires.
        """
        try:
            return build(item)
        except ValidationError as exc:
            self.skipped += 1
            level = logging.DEBUG if self.skipped > 1 else logging.WARNING
            _LOGGER.log(level, "not published (%d so far): %s", self.skipped, exc)
            return None

    def _estimate(self, item: tuple[CoreEstimate, Track3DEstimate | None]) -> models.Estimate:
        est, track = item
        self.estimate_seq += 1
        d = est.depth_m
        depth = models.DepthByEstimator(
            measured=_fin(d.get("measured")),
            cf1=_fin(d.get("cf1")),
            cf2=_fin(d.get("cf2")),
            lpv=_fin(d.get("lpv")),
            kf=_fin(d.get("kf")),
        )
        best = est.best if est.best in ("lpv", "kf", "cf2", "cf1") else self.default_best
        return models.Estimate(
            seq=self.estimate_seq,
            t=models.wall_time(),
            t_mono=est.t,
            state=est.state,
            depth_m=depth,
            best=best,
            z_m=_fin(est.z_m),
            sigma_m=nonneg(est.sigma_m),
            sigmas_m=models.SigmaByEstimator(
                **{k: nonneg(est.sigma_by.get(k)) for k in ("measured", "cf1", "cf2", "lpv", "kf")}
            )
            if est.sigma_by
            else None,
            beta_m_s=_fin(est.beta_m_s),
            size_m=nonneg(est.size_m),
            r_px=nonneg(est.r_px),
            rho_per_s=_fin(est.rho),
            position_m=_vec(track.position_m if track else est.position_world_m),
            velocity_m_s=_vec(track.velocity_m_s if track else est.velocity_world_m_s),
            acceleration_m_s2=_vec(track.acceleration_m_s2) if track else None,
            angular_speed_rad_s=_fin(track.angular_speed_rad_s) if track else None,
            position_sigma_m=_vec(track.position_sigma_m) if track else None,
            model_probabilities=dict(track.model_probabilities) if track else None,
            pan_deg=_fin(est.pan_deg) or 0.0,
            tilt_deg=_fin(est.tilt_deg) or 0.0,
            focus_counts=est.focus_counts if est.focus_counts and est.focus_counts >= 0 else None,
        )

    def _measurement(self, m: CoreMeasurement) -> models.Measurement:
        self.measurement_seq += 1
        costs = [max(0.0, _fin(c) or 0.0) for c in m.costs]
        return models.Measurement(
            seq=self.measurement_seq,
            burst=max(0, m.burst_id),
            t=models.wall_time(),
            t_mono=m.t,
            focus_counts=[max(0, int(c)) for c in m.focus_counts],
            v_mm=[_fin(v) or 0.0 for v in m.v_mm],
            costs=costs,
            fit=models.Fit(
                alpha=_fin(m.alpha),
                v_mm=_fin(m.v_hat_mm),
                residual=nonneg(m.residual),
                accepted=m.accepted,
                reason=m.reason or None,
            ),
            z_m=_fin(m.z_m),
            sigma_m=nonneg(m.sigma_m),
        )


# The fields of an estimate that follow from its depth (nulled while the gate is closed).
_NO_DEPTH: dict[str, Any] = {
    "depth_m": models.DepthByEstimator(measured=None, cf1=None, cf2=None, lpv=None, kf=None),
    "z_m": None,
    "sigma_m": None,
    "sigmas_m": None,
    "beta_m_s": None,
    "size_m": None,
    "position_m": None,
    "velocity_m_s": None,
    "acceleration_m_s2": None,
    "angular_speed_rad_s": None,
    "position_sigma_m": None,
    "model_probabilities": None,
}


def without_depth(payload: models.Estimate) -> models.Estimate:
    """``payload`` with every field that follows from the depth null (the gate is closed)."""
    return payload.model_copy(update=_NO_DEPTH)


def truth_payload(t_mono: float, truth: Any) -> models.Truth:
    """The ``…/sim/truth`` payload of the simulator's ground truth of one frame."""
    return models.Truth(
        t=models.wall_time(),
        t_mono=t_mono,
        z_m=float(truth.z_m),
        position_m=_vec(truth.position_world_m) or (0.0, 0.0, 0.0),
        size_m=float(truth.size_m) if truth.size_m > 0 else None,
        velocity_m_s=_vec(getattr(truth, "velocity_world_mps", None)),
        acceleration_m_s2=_vec(getattr(truth, "acceleration_world_mps2", None)),
        angular_speed_rad_s=_fin(getattr(truth, "angular_speed_rad_s", None)),
        in_view=_bool(getattr(truth, "in_view", None)),
    )


def _bool(value: object) -> bool | None:
    return None if value is None else bool(value)


def _fin(value: float | None) -> float | None:
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def nonneg(value: float | None) -> float | None:
    """``value`` if it is finite and not negative, else None."""
    v = _fin(value)
    return v if v is not None and v >= 0 else None


def _vec(value: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    x, y, z = (float(c) for c in value)
    if not all(math.isfinite(c) for c in (x, y, z)):
        return None
    return x, y, z
