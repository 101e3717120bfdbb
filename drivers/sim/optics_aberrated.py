"""A second lens for the simulated camera: aberrated defocus, another focus cam, a textured wall.

The reference optics (``drivers/sim/optics.py``) blur with a uniform disc and focus along a cam
quadratic in dioptres, over a uniform background. A lab's lens differs on every count, and an
estimator tuned on one simulator must be scored on another (issue 11). This model is written from
geometric optics only, independently of the estimator and of the reference lens:

* **Defocus with spherical aberration.** A ray through the normalised pupil radius ``ρ`` lands
  at the transverse radius ``t(ρ) = ρ (d + s (ρ² − 2/3))`` px: ``d`` the signed defocus (the
  rim ray of a perfect lens, ``(D/2)(v0 − v)/v / p``) and ``s`` the third-order (Seidel)
  spherical aberration at the rim, balanced by the defocus ``−2s/3`` at which the RMS spot is
  smallest. The pupil is uniformly lit, so ``u = ρ²`` is uniform: the PSF is the distribution of
  ``t`` over the pupil, rotationally symmetric, with a caustic ring on the side of focus where
  ``d`` and ``s`` have opposite signs and a soft-edged disc on the other — its shape depends on
  the sign of defocus. Its second moment is ``E[t²] = d²/2 + s²/36`` (the cross term vanishes by
  the balancing), so the *RMS* focus is at ``d = 0``: the lens table (``sharp_v_mm``, the
  ground-truth calibration) refers to the RMS focus. Diffraction, the pixel aperture and the
  analog chain add a Gaussian ``σ0``.
* **Focus cam.** The focus power is ``P = P_near [(e^{κu} − 1)/(e^κ − 1) + ε sin(2πmu)/(2πm)]``
  of the normalised counts ``u``: exponential, with a ripple (cam machining), monotone by the
  config's check — not the reference's quadratic.
* **Textured background.** A wall at ``background_depth_m`` covered with band-limited noise,
  blurred by its own defocus (disc OTF, precomputed at a ladder of radii and blended), fixed in
  the world: panning and tilting move it. The target is composited over it as a layer (its
  blurred coverage is the alpha), so the edge sees the wall through the blur.
* **Sensor.** Shot noise of variance ``signal/gain`` (Gaussian approximation of Poisson: ≥ 1000
  electrons a pixel at the default gain) on the whole frame, wall included, plus Gaussian read
  noise, rounded to 8 bits.

The outline of an irregular target (``world.target.shape = "irregular"``) is in
``drivers/sim/outline.py``.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
import numpy.typing as npt
from scipy import special

from drivers.sim.config import LensConfig, OpticsModelConfig, SensorConfig
from drivers.sim.optics import (
    BLUR_QUANTUM_PX,
    KERNEL_CACHE_SIZE,
    FrameView,
    Image8,
    Image32,
    Optics,
    Patch,
    Sensor,
    TargetImage,
    render_patch,
)

PSF_SUPERSAMPLE = 4  # sub-samples per pixel and axis when integrating the PSF over a pixel
# Ray grid floors (pupil zones along ρ, azimuths per quadrant): enough for a smooth small spot;
# larger spots get one ray per sub-sample along ρ and along the widest arc.
PUPIL_ZONES_MIN = 48
AZIMUTHS_MIN = 12
BACKGROUND_TILE_PX = 1024  # periodic wall texture (square), wider than a 640×480 frame
BACKGROUND_GRAIN_PX = 2.5  # correlation length of the wall texture (Gaussian spectrum cut-off)
# Blur radii (px) at which the wall is prefiltered; a frame blends the two around its own blur.
BACKGROUND_BLUR_LADDER_PX = (0.0, 0.75, 1.5, 3.0, 4.5, 6.5, 9.0, 13.0, 18.0, 26.0, 40.0)


class AberratedOptics(Optics):
    """The aberrated lens: same zoom and sensor geometry, its own focus cam, PSF and background."""

    def __init__(self, sensor: SensorConfig, lens: LensConfig, model: OpticsModelConfig) -> None:
        lens = lens.model_copy(
            update={
                "name": model.lens_name,
                "near_focus_m": model.near_focus_m,
                "residual_blur_px": model.residual_blur_px,
            }
        )
        super().__init__(sensor, lens)
        self.model = model

    # -- focus cam ---------------------------------------------------------------------------
    def focus_power_dpt(self, focus_counts: float) -> float:
        """P(counts): exponential cam with a ripple (see the module docstring)."""
        lens = self.lens
        u = (focus_counts - lens.focus_far_counts) / (
            lens.focus_near_counts - lens.focus_far_counts
        )
        return _cam(u, self.model) / lens.near_focus_m

    def focus_counts_for_depth(self, z_m: float) -> float:
        """Counts focusing at ``z_m`` (bisection of the monotone cam; ends clamp)."""
        lens = self.lens
        target = 0.0 if math.isinf(z_m) else lens.near_focus_m / z_m
        lo, hi = 0.0, 1.0
        if target <= 0.0:
            u = 0.0
        elif target >= 1.0:
            u = 1.0
        else:
            for _ in range(60):  # 2^-60 of the range: exact in double precision
                mid = 0.5 * (lo + hi)
                if _cam(mid, self.model) < target:
                    lo = mid
                else:
                    hi = mid
            u = 0.5 * (lo + hi)
        return lens.focus_far_counts + u * (lens.focus_near_counts - lens.focus_far_counts)

    # -- PSF -----------------------------------------------------------------------------------
    def signed_defocus_px(self, v0_mm: float, v_mm: float, zoom_counts: float) -> float:
        """Rim-ray defocus d = (D/2)(v0 − v)/v / p: > 0 with the sensor behind the image."""
        return 0.5 * self.aperture_mm(zoom_counts) * (v0_mm - v_mm) / v_mm / self.pixel_pitch_mm

    def defocus_psf(self, v0_mm: float, v_mm: float, zoom_counts: float) -> Image32:
        """The aberrated PSF of a point sharp at ``v_mm`` with the sensor at ``v0_mm``."""
        return self.psf_signed(self.signed_defocus_px(v0_mm, v_mm, zoom_counts))

    def psf_signed(self, defocus_px: float) -> Image32:
        """Normalised PSF for a signed rim defocus (cached on a 0.02 px grid)."""
        quantised = round(round(defocus_px / BLUR_QUANTUM_PX) * BLUR_QUANTUM_PX, 6)
        return _ray_psf(quantised, self.model.spherical_px, self.lens.residual_blur_px)

    def psf(self, blur_radius_px: float) -> Image32:
        """PSF for an unsigned blur radius: the sensor-behind-focus side (d = +b)."""
        return self.psf_signed(abs(blur_radius_px))

    def psf_second_moment_px2(self, defocus_px: float) -> float:
        """E[x²] per axis of the PSF (ray part d²/4 + s²/72, plus σ0²; pixel aperture apart)."""
        s = self.model.spherical_px
        return 0.25 * defocus_px**2 + s * s / 72.0 + self.lens.residual_blur_px**2

    # -- rendering -------------------------------------------------------------------------------
    def render_target(
        self,
        target: TargetImage,
        background_dn: float,
        kernel: Image32,
        motion_px: tuple[float, float],
    ) -> Patch | None:
        """The target layer with its blurred coverage as alpha (composited by the sensor)."""
        patch = render_patch(target, background_dn, kernel, motion_px, self.frame_size)
        if patch is None:
            return None
        contrast = target.foreground_dn - background_dn
        if target.texture is None and abs(contrast) > 1e-3:
            alpha = (patch.image - np.float32(background_dn)) * np.float32(1.0 / contrast)
        else:  # a textured face: render the coverage alone
            cover = TargetImage(target.outline_px, 1.0)
            alone = render_patch(cover, 0.0, kernel, motion_px, self.frame_size)
            if alone is None:
                return None
            alpha = alone.image
        return Patch(patch.image, patch.x0, patch.y0, np.asarray(alpha, dtype=np.float32))

    def make_sensor(self) -> Sensor:
        """A sensor that composites over the textured wall."""
        return WallSensor(self)

    def background_image(self, view: FrameView, background_dn: float) -> Image32:
        """The wall as this frame sees it: shifted by pan/tilt, blurred by its own defocus."""
        width, height = self.frame_size
        zoom = view.zoom_counts
        scale = self.scale_px(view.v0_mm, zoom)
        v_wall = self.sharp_v_mm(self.model.background_depth_m, zoom)
        blur = self.blur_radius_px(view.v0_mm, v_wall, zoom)
        ladder = BACKGROUND_BLUR_LADDER_PX
        k = int(np.searchsorted(ladder, blur, side="right")) - 1
        k = min(max(k, 0), len(ladder) - 2)
        w = min(max((blur - ladder[k]) / (ladder[k + 1] - ladder[k]), 0.0), 1.0)
        tiles = _wall_tiles(self.model.background_seed, BACKGROUND_TILE_PX, height, width)
        n = BACKGROUND_TILE_PX
        ox = round(scale * math.radians(view.pan_deg)) % n
        oy = round(-scale * math.radians(view.tilt_deg)) % n
        a = tiles[k][oy : oy + height, ox : ox + width]
        b = tiles[k + 1][oy : oy + height, ox : ox + width]
        wall = cv2.addWeighted(a, 1.0 - w, b, w, 0.0)
        gain = np.float32(self.model.background_contrast_dn)
        return np.asarray(wall * gain + np.float32(background_dn), dtype=np.float32)


class WallSensor(Sensor):
    """Exposes the target layer over the textured wall, with signal-dependent noise everywhere."""

    def __init__(self, optics: AberratedOptics) -> None:
        super().__init__(optics.sensor)
        self._optics = optics

    def expose(
        self, background_dn: float, patch: Patch | None, seed: int, view: FrameView | None = None
    ) -> Image8:
        """Wall (if ``view`` is given, else uniform) + target layer + shot and read noise."""
        cfg = self.config
        cv2.setRNGSeed(seed & 0x7FFFFFFF)
        cv2.randn(self._noise, np.zeros(1), np.ones(1))
        if view is None or background_dn <= 0.0:
            signal = np.full((cfg.height_px, cfg.width_px), background_dn, dtype=np.float32)
        else:
            signal = self._optics.background_image(view, background_dn)
        if patch is not None:
            h, w = patch.image.shape
            fx0, fy0 = max(patch.x0, 0), max(patch.y0, 0)
            fx1, fy1 = min(patch.x0 + w, cfg.width_px), min(patch.y0 + h, cfg.height_px)
            if fx1 > fx0 and fy1 > fy0:
                rows = slice(fy0 - patch.y0, fy1 - patch.y0)
                cols = slice(fx0 - patch.x0, fx1 - patch.x0)
                layer = patch.image[rows, cols]
                wall = signal[fy0:fy1, fx0:fx1]
                if patch.alpha is None:
                    wall[...] = layer
                else:  # the layer was blended with a uniform background_dn: swap in the wall
                    behind = np.float32(1.0) - patch.alpha[rows, cols]
                    wall[...] = layer + behind * (wall - np.float32(background_dn))
        read2 = np.float32(cfg.read_noise_dn**2)
        if cfg.gain_e_per_dn > 0:
            var = np.maximum(signal, np.float32(0.0)) * np.float32(1.0 / cfg.gain_e_per_dn) + read2
        else:
            var = np.full_like(signal, read2)
        frame = signal + np.sqrt(var) * self._noise
        np.maximum(frame, 0.0, out=frame)
        return np.asarray(cv2.convertScaleAbs(frame), dtype=np.uint8)


# -- private helpers ------------------------------------------------------------------------


def _cam(u: float, model: OpticsModelConfig) -> float:
    """Normalised focus power of the normalised counts (0 at infinity, 1 at the near end)."""
    kappa, eps, m = model.focus_exponent, model.focus_ripple, model.focus_ripple_cycles
    base = u if kappa == 0.0 else math.expm1(kappa * u) / math.expm1(kappa)
    return base + eps * math.sin(2.0 * math.pi * m * u) / (2.0 * math.pi * m)


@functools.lru_cache(maxsize=KERNEL_CACHE_SIZE)
def _ray_psf(defocus_px: float, spherical_px: float, sigma0_px: float) -> Image32:
    """Rays through a uniformly lit pupil splatted on the sensor, integrated over pixels, ⊛ σ0.

    Rays on a polar grid of the pupil (ρ midpoints weighted by ρ: equal-area, so the weights are
    exact) over one quadrant of azimuth, splatted bilinearly on a sub-sampled grid symmetric
    about the centre, then mirrored into the other three quadrants: the PSF's mass and its second
    moment are those of the ray distribution (plus the splat's and the pixel's box variances).
    Grid spacing ≤ one sub-sample along ρ and along the widest arc.
    """
    ss = PSF_SUPERSAMPLE
    slope = abs(defocus_px) + 2.5 * abs(spherical_px)  # bound on |dt/dρ|
    n_rho = max(PUPIL_ZONES_MIN, math.ceil(slope * ss))
    rho = (np.arange(n_rho, dtype=np.float64) + 0.5) / n_rho
    t = rho * (defocus_px + spherical_px * (rho * rho - 2.0 / 3.0))
    r_max = float(np.abs(t).max())
    n_phi = max(AZIMUTHS_MIN, math.ceil(0.5 * math.pi * r_max * ss))
    phi = (np.arange(n_phi, dtype=np.float64) + 0.5) * (0.5 * math.pi / n_phi)
    half = math.ceil(r_max + 3.0 * sigma0_px) + 1
    size = 2 * half + 1
    n = size * ss
    centre = (half + 0.5) * ss - 0.5
    x = (centre + ss * t[:, None] * np.cos(phi)[None, :]).ravel()
    y = (centre + ss * t[:, None] * np.sin(phi)[None, :]).ravel()
    weight = np.repeat(rho / float(rho.sum()), n_phi) / n_phi
    fine = _splat(x, y, weight, n)
    fine = fine + fine[::-1, :]
    fine = fine + fine[:, ::-1]
    if sigma0_px > 0.0:
        # σ0 before the pixel integration: a smooth spot bins into pixels with the box's 1/12 px²
        # on either side of focus (a caustic ring binned raw is ±0.1 px² off, sign-dependent)
        fine = np.asarray(
            cv2.GaussianBlur(fine, (0, 0), sigma0_px * ss, borderType=cv2.BORDER_CONSTANT),
            dtype=np.float64,
        )
    kernel = fine.reshape(size, ss, size, ss).sum(axis=(1, 3))
    normalised = np.asarray(kernel / kernel.sum(), dtype=np.float32)
    normalised.setflags(write=False)
    return normalised


def _splat(
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    weight: npt.NDArray[np.float64],
    n: int,
) -> npt.NDArray[np.float64]:
    """Bilinear splat of weighted points onto an n×n grid (grid coordinates, inside the grid)."""
    ix, iy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - ix, y - iy
    base = iy * n + ix
    grid = np.zeros(n * n)
    grid += np.bincount(base, weights=weight * (1 - fx) * (1 - fy), minlength=n * n)
    grid += np.bincount(base + 1, weights=weight * fx * (1 - fy), minlength=n * n)
    grid += np.bincount(base + n, weights=weight * (1 - fx) * fy, minlength=n * n)
    grid += np.bincount(base + n + 1, weights=weight * fx * fy, minlength=n * n)
    return grid.reshape(n, n)


@functools.cache
def _wall_tiles(seed: int, n: int, height: int, width: int) -> tuple[Image32, ...]:
    """Periodic wall texture (unit peak-to-mean ≈ 1), one padded copy per ladder blur radius.

    Band-limited noise (Gaussian spectrum of correlation length BACKGROUND_GRAIN_PX), blurred by
    the disc OTF 2 J1(kb)/(kb) of each ladder radius b; each copy is padded by wrap-around to
    (n + height) × (n + width) so that any frame window is a plain slice.
    """
    rng = np.random.default_rng([seed, 0xBA5E])
    white = rng.standard_normal((n, n))
    spectrum = np.fft.rfft2(white)
    ky = np.fft.fftfreq(n)[:, None] * 2.0 * math.pi
    kx = np.fft.rfftfreq(n)[None, :] * 2.0 * math.pi
    k = np.sqrt(kx * kx + ky * ky)
    spectrum *= np.exp(-0.5 * (k * BACKGROUND_GRAIN_PX) ** 2)
    base = np.fft.irfft2(spectrum, s=(n, n))
    base /= 3.0 * float(base.std())  # ±1 ≈ ±3σ
    spectrum = np.fft.rfft2(base)
    tiles = []
    for b in BACKGROUND_BLUR_LADDER_PX:
        if b == 0.0:
            img = base
        else:
            kb = np.maximum(k * b, 1e-12)
            otf = 2.0 * special.j1(kb) / kb
            img = np.fft.irfft2(spectrum * otf, s=(n, n))
        padded = np.pad(img, ((0, height), (0, width)), mode="wrap").astype(np.float32)
        padded.setflags(write=False)
        tiles.append(padded)
    return tuple(tiles)
