"""Payload conversion: the core's outputs → the MQTT payload models (``dffd.mqtt.models``).

Non-finite numbers become null, negative sizes and σ are dropped, and every payload is
numbered per kind. An output that does not fit its schema is skipped and counted, never fatal.

Publish gate (:class:`FirstDepthGate`): after a start or a loss the core initialises its filters
from the first accepted burst, also when its vertex lay outside the bracket (extrapolated). The
first burst of a start spans most of the focus range, where the cost is far from a parabola:
live on the default demo its extrapolated vertex put the target at 15.2 m (σ 0.76 m) while it
was at 10.0 m, and the first four estimates said 14.4-15.1 m with σ 0.72-0.75 m (a 6-7σ error).
So depths are published only once a burst with its vertex inside its bracket has been taken
(or :data:`FIRST_DEPTH_MAX_BURSTS` accepted bursts, so a target that keeps outrunning its
brackets is not hidden for ever); until then estimates go out with their depth fields null.
The ``…/measurement`` payloads of those bursts are published as they are, with their reason.
The first burst's vertex can also fall *inside* its (full-range) bracket and far from the target:
after a release and an automatic re-acquisition on the demo it read 10.5 m for a target at 8.1 m
and the first estimate said 11.6 m — with σ 18 m. So the gate also waits until the best
estimate's own σ is at most its depth (:data:`FIRST_DEPTH_MAX_REL_SIGMA`: a depth whose 1σ
exceeds it does not even say its order of magnitude), or :data:`FIRST_DEPTH_FORCE_BURSTS`
accepted bursts. The first depths of normal starts pass at once: σ 0.17-0.19 m at 9.8 m on the
demo, 1.05 m at 3.97 m on the static world (the filters' start-up σ; 26 %).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from dffd.core.focus import REASON_OK
from dffd.core.pipeline import Estimate as CoreEstimate
from dffd.core.pipeline import Measurement as CoreMeasurement
from dffd.core.tracking3d import Track3DEstimate
from dffd.mqtt import models

_LOGGER = logging.getLogger(__name__)

_M = TypeVar("_M", bound=BaseModel)
_T = TypeVar("_T")

# Accepted bursts after which depths are published even if every one was extrapolated: the
# scheduler centres each next bracket on the last vertex, so on the default demo the second
# burst already brackets it (measured: 1 extrapolated first burst per start, none after).
FIRST_DEPTH_MAX_BURSTS = 3
# The first published depth's 1σ is at most this fraction of it (normal starts: 2-26 %; the wild
# first burst above: 157 %), unless this many bursts were accepted (~3 s of bursts).
FIRST_DEPTH_MAX_REL_SIGMA = 1.0
FIRST_DEPTH_FORCE_BURSTS = 6

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


class FirstDepthGate:
    """Whether the core's depths may be published yet (see the module docstring)."""

    def __init__(self) -> None:
        self.open = False
        self._bracketed = False  # a burst inside its bracket (or enough bursts) since reset
        self._accepted = 0  # accepted bursts since the filters were (re)initialised
        self.withheld = 0  # estimates published with their depths nulled, since start

    def on_measurement(self, m: CoreMeasurement) -> None:
        """A burst closed: an accepted one inside its bracket readies the gate."""
        if not m.accepted:
            return
        self._accepted += 1
        if m.reason in ("", REASON_OK) or self._accepted >= FIRST_DEPTH_MAX_BURSTS:
            self._bracketed = True

    def passes(self, est: CoreEstimate) -> bool:
        """True when ``est``'s depths may be published; an estimate without depths (filters
        not initialised: start, loss, release) closes the gate again."""
        if all(z is None for z in est.depth_m.values()):
            self.open = self._bracketed = False
            self._accepted = 0
            return True
        if not self.open and self._bracketed:
            z, sigma = est.z_m, est.sigma_m
            precise = z is not None and sigma is not None and sigma <= FIRST_DEPTH_MAX_REL_SIGMA * z
            self.open = precise or self._accepted >= FIRST_DEPTH_FORCE_BURSTS
        if not self.open:
            self.withheld += 1
        return self.open


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
