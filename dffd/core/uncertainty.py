"""The σ each estimator publishes (docs/estimation.md §9), from its error covariance.

:class:`Uncertainty` runs one error covariance (:mod:`dffd.core.error_covariance`) per
estimator next to the filters, adapts the measurement noise, the process noise and the
slow-error factor from the size invariant (:mod:`dffd.core.noise`), and publishes
``σ = √(P_zz ι) × t-factor`` per estimator (docs/estimation.md §9, §14, §17). Pure.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dffd.core.error_covariance import ErrorCovariance, SharedFrameCovariance
from dffd.core.filters import KFNoise, LPVGains, exp_input2_floats
from dffd.core.noise import (
    DriftRate,
    InnovationScale,
    NoiseAdaptConfig,
    SlowErrors,
    TimeOffset,
    shared_frame_correlation,
)

FloatArray = npt.NDArray[np.float64]

FIXED_GAIN = ("cf1", "cf2", "lpv")


class Uncertainty:
    """Per-estimator error covariances, the adapted measurement noise and time offset."""

    def __init__(
        self,
        noise: KFNoise,
        adapt: NoiseAdaptConfig,
        *,
        cf1_k: float,
        cf2_gains: tuple[float, float],
        lpv: LPVGains,
    ) -> None:
        self.noise = noise
        self.adapt = adapt
        # λ: true/stated measurement variance, from consecutive size measurements (no dynamics)
        self.scale = InnovationScale(adapt)
        # κ²: the KF's normalised innovations (NIS) against their predicted variance, a
        # diagnostic only since docs/estimation.md §17: it measured what ι measures (slow
        # measurement errors) plus the measurement noise λ already scales, and its floor of 1
        # only ever widened the σ
        self.consistency = InnovationScale(adapt)
        self.offset = TimeOffset(adapt)
        self.slow = SlowErrors(adapt)
        self.drift = DriftRate(adapt)
        self._last_size: tuple[float, float, tuple[int, ...]] | None = None
        self._sizes = 0  # size measurements seen
        self._cf1_k = cf1_k
        self._cf2 = cf2_gains
        self._lpv = lpv
        # the σ each estimator publishes: per unit λ, the shared frame as MA(1) (§23)
        self.errors = {
            "cf1": SharedFrameCovariance(1),
            "cf2": SharedFrameCovariance(2),
            "lpv": SharedFrameCovariance(2),
            "kf": SharedFrameCovariance(2),
        }
        # the Kalman filter's error as before §23 (λ̂ of each burst's time, the shared frame as
        # AR(1)): what the start-up hand-over rule and κ² were chosen on, kept so that no
        # estimate changes (EstimatorBank._seeding reads kf_covariance)
        self._kf_model = ErrorCovariance(2)
        self._frames: tuple[int, ...] = ()
        self._weights: tuple[float, float] | None = None  # the last set by _set_weights
        self.measured_sigma: float | None = None  # adapted σ of the last measurement
        self.started = False

    @property
    def time_offset_s(self) -> float:
        """τ̂: a depth measurement refers to its frames' mean exposure time plus this."""
        return self.offset.tau_s

    def measurement_sigma(self, sigma_fit: float) -> float:
        """The fit's σ scaled by the adapted noise ratio: the σ the filters are told."""
        return sigma_fit * math.sqrt(self.scale.scale)

    def sigma(self, name: str) -> float | None:
        """Published σ of estimator ``name`` (None before the filters start)."""
        return self.sigmas({name: 0.0})[name]

    def sigmas(self, depth: dict[str, float | None]) -> dict[str, float | None]:
        """Published σ of every estimator with a value in ``depth`` (None for the others):
        ``√(P_zz ι) × t-factor``, ``P_zz`` at the current λ̂ (docs/estimation.md §17, §23)."""
        if not self.started:
            return dict.fromkeys(depth)
        self._set_weights()
        f = self.factor
        iota = math.sqrt(self.slow.factor)
        out: dict[str, float | None] = {}
        for name, value in depth.items():
            err = self.errors.get(name)
            if value is None:
                out[name] = None
            elif name == "measured":
                out[name] = None if self.measured_sigma is None else self.measured_sigma * f
            else:
                out[name] = None if err is None else math.sqrt(err.var_z) * iota * f
        return out

    @property
    def factor(self) -> float:
        """Student-t inflation for the degrees of freedom of the noise estimates λ and ι (the
        relative variances of the two add)."""
        return self.scale.factor

    def start(self, sigma_meas: float, frames: tuple[int, ...]) -> None:
        """The Kalman filter starts at a measurement of σ ``sigma_meas`` (the others follow)."""
        var = sigma_meas * sigma_meas  # λ̂ is its prior 1 here: per unit λ too
        n = self.noise
        for kf in (self.errors["kf"], self._kf_model):
            if n.sigma_b > 0 and kf.pb is not None:
                # b's prior σ_b0 is the KF's model of a disturbance, as its b walk is: carried
                # in the b part (as σ_b0²/σ_b² of a unit walk), so it goes when the data's
                # process noise replaces the KF's (on a rigid target b shows in the size
                # invariant)
                kf.start(var, 0.0)
                kf.pb[3] = (n.sigma_b0 / n.sigma_b) ** 2
            else:
                kf.start(var, n.sigma_b0**2)
        for name in FIXED_GAIN:
            self.errors[name].copy_from(self.errors["kf"])
        self._frames = frames
        self.measured_sigma = sigma_meas
        self.started = True

    def predict(self, dt: float, ratio: float, rho: float, z: float) -> None:
        """Propagate every error covariance over one step of the filters."""
        if not self.started or dt <= 0:
            return
        self._set_weights()
        # unit process noises: a random walk of ln z (variance z² dt) and of b (variance dt)
        qz = (z * z * dt, 0.0, 0.0, 0.0)
        qb = (0.0, 0.0, 0.0, dt)
        lam = -rho
        # CF1: ẑ' = −k ẑ + k y + ψ
        k = self._cf1_k
        e = math.exp(-k * dt)
        near = abs(lam + k) * dt < 1e-9
        g1 = k * dt * e if near else k * (math.exp(lam * dt) - e) / (lam + k)
        self.errors["cf1"].propagate((e, 0.0, 0.0, 0.0), (g1, 0.0), ratio, qz, qb)
        k1, k2 = self._cf2
        phi, g = exp_input2_floats((-k1, 1.0, -k2, 0.0), (k1, k2), lam, dt)
        self.errors["cf2"].propagate(phi, g, ratio, qz, qb)
        gl = self._lpv
        kl = gl.k1_0 - min(max(rho, gl.rho_min), gl.rho_max)
        phi, g = exp_input2_floats((-rho - kl, 1.0, -gl.k2, 0.0), (kl, gl.k2), lam, dt)
        self.errors["lpv"].propagate(phi, g, ratio, qz, qb)
        # the KF's own transition (its b enters through g_k), no held measurement in between;
        # its b walk as DepthKF.predict: integrated over the step
        lr = -math.log(max(ratio, 1e-6))
        gk = dt if abs(lr) < 1e-9 else dt * (1.0 - ratio) / lr
        qb_kf = (dt * dt * dt / 3.0, dt * dt / 2.0, dt * dt / 2.0, dt)
        phi_kf = (ratio, gk, 0.0, 1.0)
        self.errors["kf"].propagate(phi_kf, (0.0, 0.0), ratio, qz, qb_kf)
        self._kf_model.propagate(phi_kf, (0.0, 0.0), ratio, qz, qb_kf)

    def process_weights(self) -> tuple[float, float]:
        """(w_z, w_b): intensities of the ln z and b random walks. The Kalman filter's
        (σ_ρ², σ_b²) until ``drift_min_bursts`` size measurements have been seen (and always
        with ``process_noise = "kf"``); none after (``"data"``): on a rigid target whatever makes
        ``ż = −ρz`` drift from the truth shows in the size invariant as a slow measurement error,
        which ι already counts (docs/estimation.md §19); the size invariant's random-walk rate
        q̂ (DriftRate) with ``"drift"`` (§14). Applied to every estimator's whole history
        (ErrorCovariance)."""
        n = self.noise
        mode = self.adapt.process_noise
        if mode == "kf" or self._sizes < self.adapt.drift_min_bursts:
            return n.sigma_rho**2, n.sigma_b**2
        if mode == "drift":
            q = self.drift.rate
            return (n.sigma_rho**2, n.sigma_b**2) if q is None else (q, 0.0)
        return 0.0, 0.0

    def _set_weights(self) -> None:
        w = self.process_weights()
        if w == self._weights:
            return  # every covariance has them already (and no b walk if w_b is 0)
        self._weights = w
        for err in (*self.errors.values(), self._kf_model):
            err.weights = w
            if w[1] == 0.0 and err.pb is not None:
                err.drop_b_walk()  # the data's process noise has no b walk: for good

    def observe_size(
        self,
        log_size: float,
        rho: float,
        rel_sigma_fit: float,
        frames: tuple[int, ...],
        t: float = math.nan,
    ) -> float:
        """A burst's size measurement ``ln(z_m s(t_b))`` at size rate ``rho`` with the fit's
        relative σ: update λ from its difference to the previous one (the size invariant holds
        whatever the target does, so the difference is measurement noise only) and τ̂
        (returned)."""
        last, self._last_size = self._last_size, (log_size, rel_sigma_fit, frames)
        corr_now = 0.0 if last is None else shared_frame_correlation(last[2], frames)
        self.slow.update(log_size, rel_sigma_fit, corr_now)
        if math.isfinite(log_size) and rel_sigma_fit > 0:
            self._sizes += 1
        if self.adapt.process_noise == "drift":  # its least squares only where it is used
            self.drift.update(t, log_size, rel_sigma_fit)
        if last is not None:
            prev, prev_sigma, prev_frames = last
            corr = shared_frame_correlation(prev_frames, frames)
            var_d = rel_sigma_fit**2 + prev_sigma**2 - 2.0 * corr * rel_sigma_fit * prev_sigma
            self.scale.update(log_size - prev, self.scale.scale * var_d)
            for cov in self.errors.values():
                cov.scale = self.scale.scale  # the whole history at the current λ̂ (§23)
        var = self.scale.scale * rel_sigma_fit * rel_sigma_fit
        return self.offset.update(log_size, rho, var)

    def measurement(
        self,
        innovation: float,
        sigma_fit: float,
        kf_p: FloatArray,
        frames: tuple[int, ...],
    ) -> float:
        """An accepted burst: check the KF's innovation (``y − ẑ⁻``) against its predicted
        variance (κ²), replace the held measurement everywhere, apply the KF's update; returns
        the σ the KF is told (the fit's, scaled by λ)."""
        corr = shared_frame_correlation(self._frames, frames)
        # Sage–Husa: κ² is updated by ν²/S with S as the published σ states it (κ² included).
        # With S alone the fixed point is E[ν²/S] = 1 whatever κ² is: κ² was a multiplicative
        # random walk held above its floor of 1, and climbed to 4–6 on paper-circle while
        # E[ν²/S] was 1.1 (docs/estimation.md §9)
        s = self.innovation_variance(sigma_fit, frames) * self.consistency.scale
        self.consistency.update(innovation, s)
        self._frames = frames
        sigma = self.measurement_sigma(sigma_fit)
        var = sigma * sigma
        p00 = float(kf_p[0, 0])
        den = p00 + var
        gain = (p00 / den, float(kf_p[1, 0]) / den)  # the KF's, told λ̂-scaled noise
        for err in self.errors.values():
            err.replace_measurement(sigma_fit * sigma_fit, corr)  # per unit λ
        self.errors["kf"].kalman_update(gain)
        self._kf_model.replace_measurement(var, corr)
        self._kf_model.kalman_update(gain)
        self.measured_sigma = sigma
        return sigma

    def innovation_variance(self, sigma_fit: float, frames: tuple[int, ...]) -> float:
        """Predicted variance of the KF's innovation for a burst of fit σ ``sigma_fit`` on
        ``frames`` (its error and the new measurement's, with the current λ; κ² not included)."""
        self._set_weights()
        probe = self._kf_model.clone()
        probe.replace_measurement(
            self.measurement_sigma(sigma_fit) ** 2, shared_frame_correlation(self._frames, frames)
        )
        return probe.innovation_variance()

    def kf_covariance(self) -> tuple[float, float, float, float]:
        """The KF's [z, b] error covariance (row-major) at the current process noise, as the
        start-up hand-over rule was chosen on (each burst at its time's λ̂, AR(1); §19, §23)."""
        self._set_weights()
        p00, p01, p10, p11 = self._kf_model.error_block()
        return p00, p01, p10, p11

    def hand_over(self) -> None:
        """The fixed-gain filters were seeded from the KF: they inherit its error covariance."""
        for name in FIXED_GAIN:
            self.errors[name].copy_from(self.errors["kf"])
