"""The bank of depth estimators that run side by side on the same measurements (pure).

CF1 (known size), CF2 (unknown size, bias estimation), the LPV observer and the time-varying
Kalman filter (:mod:`dffd.core.filters`) all *predict* at every frame with the target's normalised
size ``s`` (``z s = R``: the transition over a step is exactly ``s_k/s_{k+1}``) and are *corrected*
by each accepted burst, whose depth ``z_m`` becomes a size measurement ``R_m = z_m s(t_b)``; at
later frames every estimator sees ``y = R_m / s`` (docs/estimation.md §2). The bank also
carries every estimator's error covariance and the adapted measurement noise
(:mod:`dffd.core.uncertainty`, docs/estimation.md §9).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from dffd.core.filters import CF1, CF2, DepthKF, KFTraceEvent, LPVGains, LPVObserver
from dffd.core.filters import cf2_gains as _cf2_gains
from dffd.core.lens import Lens
from dffd.core.noise import model_sigma_v_mm
from dffd.core.outputs import ESTIMATORS, EstimatorName, Measurement
from dffd.core.uncertainty import Uncertainty

if TYPE_CHECKING:
    from dffd.core.pipeline_config import PipelineConfig

__all__ = ["EstimatorBank"]


class EstimatorBank:
    """CF1, CF2, LPV and KF on one target; created empty, initialised by the first burst."""

    def __init__(self, config: PipelineConfig, lens: Lens) -> None:
        self.config = config
        self.lens = lens
        self.cf2_gains = _cf2_gains(config.cf2_sigma_psi, config.cf2_sigma_beta, config.cf2_sigma_z)
        self.lpv_gains = LPVGains.from_poles(
            config.lpv_omega, config.lpv_zeta, config.rho_min, config.rho_max
        )
        self.known_size: float | None = config.known_size_m
        self.kf_trace: list[KFTraceEvent] | None = None  # see record_kf
        self.reset()

    def record_kf(self, trace: list[KFTraceEvent]) -> None:
        """Append every Kalman-filter step to ``trace`` from now on (dffd.core.smoother)."""
        self.kf_trace = trace
        self.kf.trace = trace

    def reset(self) -> None:
        """Forget the target: no depth until the next accepted burst."""
        cfg = self.config
        self.cf1 = CF1(cfg.cf1_k)
        self.cf2 = CF2(*self.cf2_gains)
        self.lpv = LPVObserver(self.lpv_gains)
        self.kf = DepthKF(cfg.kf_noise, self.kf_trace)
        self.unc = Uncertainty(
            cfg.kf_noise,
            cfg.noise_adapt,
            cf1_k=cfg.cf1_k,
            cf2_gains=self.cf2_gains,
            lpv=self.lpv_gains,
        )
        self.size_meas: float | None = None  # R_m of the last accepted burst
        self.size_meas_sigma: float | None = None  # its σ (the burst's σ_z, relative)
        self.cf2_size: float | None = cfg.cf2_nominal_size_m
        self.n_accepted = 0
        self.initialised = False
        self._handed_over = False  # the start-up seeding has ended (see _seeding)
        self._seed_cost: float | None = None  # the KF's error cost at the previous burst

    def set_known_size(self, meters: float | None) -> None:
        """Set (enables CF1, restarted) or clear the target's known size."""
        self.known_size = meters
        self.cf1 = CF1(self.config.cf1_k)

    def depth(self, name: EstimatorName) -> float | None:
        """The depth of estimator ``name`` (not ``measured``), None before the first burst."""
        if not self.initialised:
            return None
        if name == "cf1":
            return self.cf1.z if self.known_size is not None else None
        if name == "cf2":
            return self.cf2.z
        if name == "lpv":
            return self.lpv.z
        if name == "kf":
            return self.kf.z
        return None

    def depths(self, measured: float | None) -> dict[str, float | None]:
        """Every estimator's depth in ``ESTIMATORS``' order (``measured`` first, as given), all
        None before the first burst: :meth:`depth` of each name in one call (every frame)."""
        if not self.initialised:
            return dict.fromkeys(ESTIMATORS)
        return {
            "measured": measured,
            "cf1": self.cf1.z if self.known_size is not None else None,
            "cf2": self.cf2.z,
            "lpv": self.lpv.z,
            "kf": self.kf.z,
        }

    @property
    def sigma(self) -> float | None:
        """The Kalman filter's σ (the scheduler's proxy for the prediction's uncertainty)."""
        return self.kf.sigma

    def sigmas(self, depth: dict[str, float | None]) -> dict[str, float | None]:
        """The published σ of every estimator with a depth in ``depth``: its propagated σ and
        the lens table's own error at that depth (a bias all its measurements share)."""
        out = self.unc.sigmas(depth)
        lens = self.lens
        if lens.table_sigma_v_mm > 0 or lens.table_sigma_v_at:
            for name, sigma in out.items():
                z = depth.get(name)
                if sigma is not None and z is not None and z > 0:
                    v = lens.v_from_depth(z)
                    # the table's σ where this depth is (per calibrated depth, or one number)
                    sv = lens.table_sigma_v_mm_at(v)
                    out[name] = math.hypot(sigma, abs(lens.dz_dv(v)) * sv)
        return out

    def predict(self, dt: float, s: float, s_prev: float, sdot: float, rho: float) -> None:
        """Step every estimator over ``dt`` > 0 from the size ``s_prev`` to ``s`` (initialised)."""
        assert self.size_meas is not None
        # the last size measurement seen at the image size: y(τ) = R_m / s(τ) = y0 e^{−ρτ}
        y0 = self.size_meas / s_prev
        lam = -rho
        if self.config.psi_source == "step":
            inv_rate = (1.0 / s - 1.0 / s_prev) / dt  # d(1/s)/dt over the step, exact
        else:
            inv_rate = -sdot / (s * s)
        if self.known_size is not None:
            self.cf1.step(dt, y0, inv_rate * self.known_size, lam)
        cf2_size = self.cf2_size if self.cf2_size is not None else self.size_meas
        self.cf2.step(dt, y0, inv_rate * cf2_size, lam)
        self.lpv.step(dt, rho, y0, lam)
        self.kf.predict(s_prev / s, dt)
        self.unc.predict(dt, s_prev / s, rho, self.kf.z or y0)

    def correct(self, m: Measurement, s_b: float, s: float, rate: float) -> None:
        """Apply the accepted burst ``m``, seen at the size ``s_b`` of its (transported) time
        and now at the size ``s``; ``rate`` = the filtered ρ̂ (for the online time offset)."""
        cfg = self.config
        assert m.z_m is not None
        assert m.sigma_m is not None
        z_m = m.z_m
        # the fit's σ (cost noise) and the parabola model's error at the vertex's offset
        sigma_z = math.hypot(
            m.sigma_m,
            abs(self.lens.dz_dv(m.v_hat_mm))
            * model_sigma_v_mm(m.v_mm, m.v_hat_mm, cfg.focus_measure),
        )
        # the lean τ̂ of the vertex, estimated online on the size invariant (noise.py)
        tau = self.unc.observe_size(math.log(z_m * s_b), rate, sigma_z / z_m, m.frame_indices, m.t)
        s_b *= math.exp(rate * tau)
        size_m = z_m * s_b
        self.size_meas = size_m
        self.size_meas_sigma = sigma_z * s_b
        y_now = size_m / s
        sigma_now = sigma_z * y_now / z_m
        self.n_accepted += 1
        if self.n_accepted <= cfg.cf2_size_bursts and cfg.cf2_nominal_size_m is None:
            n = self.n_accepted
            prev_size = self.cf2_size if self.cf2_size is not None else size_m
            self.cf2_size = prev_size + (size_m - prev_size) / n  # running mean
        if not self.initialised:
            # b known at 0 until the first update gives the target's speed (DepthKF.open_b)
            self.kf.reset(y_now, max(sigma_now, 1e-3), sigma_b=0.0)
            self.unc.start(max(sigma_now, 1e-3), m.frame_indices)
            self.initialised = True
        else:
            if self.n_accepted == 2:
                self.kf.open_b(rate * y_now)  # |ż| = |ρ| z at the first update
                self._seed_cost = None  # the KF's cost is compared from b's prior on
            # the noise the KF is told is adapted from its innovations (noise.py)
            innov = y_now - (self.kf.z or y_now)
            kf_sigma = self.unc.measurement(innov, sigma_now, self.kf.p, m.frame_indices)
            self.kf.update(y_now, kf_sigma)
        if self._seeding(cfg.warmup_bursts):
            self._hand_over(y_now)

    def _seeding(self, count: int | None) -> bool:
        """Whether this burst still seeds the fixed-gain filters from the KF (start-up).

        With a ``count``, the first ``count`` accepted bursts. Without (the default), while the
        KF's error still costs the LPV less than at the previous burst: an error ``[e_z, e_b]``
        handed to the LPV adds ``(e_z² + e_b²/k2)/(2 k1)`` of integrated squared depth error
        (the Gramian of its fixed error dynamics ``[[−k1, 1], [−k2, 0]]``), so seeding from the KF
        pays while the KF's covariance still shrinks in that measure; once it does not, the KF
        has converged and seeding only passes its noise on (docs/estimation.md §19).
        """
        if count is not None:
            return self.n_accepted <= count
        if self._handed_over:
            return False
        p = self.unc.kf_covariance()
        g = self.lpv_gains
        cost = (p[0] + p[3] / g.k2) / (2.0 * g.k1_0)
        last, self._seed_cost = self._seed_cost, cost
        if last is not None and cost >= last:
            self._handed_over = True
            return False
        return True

    def _hand_over(self, y_now: float) -> None:
        """Seed the fixed-gain filters from the KF's estimate (start-up, see ``_seeding``)."""
        z0 = self.kf.z if self.kf.z is not None else y_now
        b0 = self.kf.b if self.kf.b is not None else 0.0
        self.cf1.reset(z0)
        self.cf2.reset(z0)
        self.lpv.reset(z0, b0)
        self.unc.hand_over()
