"""Synthetic scenes for tests and benchmarks: a sharp-edged disc, defocused and noisy.

This is a stand-in for the optics simulator (``drivers/sim``), deliberately *not* the estimator's
model: the defocus PSF here is a pillbox (uniform disc) of the geometric blur-circle radius,
convolved with a small Gaussian residual blur, whereas the estimator assumes Gaussian spreads
adding in quadrature. Image scale ``f/p`` (pinhole) or ``v0/p`` with ``breathing``. Focus-measure
tests also blur with a Gaussian of the disc's second moment and with an aberrated defocus (rays
through the pupil with spherical aberration: a ring on one side of focus, a peaked disc on the
other), all of the same per-axis variance ``b²/4`` plus a constant.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.lens import MM_PER_M, Lens
from dffd.core.types import FrameTag
from drivers.frames import Frame

Trajectory = Callable[[float], tuple[float, float, float]]  # t -> camera-frame position (m)
Psf = Literal["disc", "gaussian", "aberrated"]
# Below this residual blur the defocus kernel is box-integrated instead of sampled (a sampled
# kernel needs a smooth PSF to keep its second moment).
SAMPLED_KERNEL_MIN_SIGMA_PX = 0.5


@dataclass(frozen=True, slots=True)
class DiscScene:
    """A flat disc of radius ``radius_m`` facing the camera; image 640×480 by default."""

    radius_m: float = 0.03576  # docs/design.md §10: sqrt(tr Σ) of a disc boundary is its radius
    width: int = 640
    height: int = 480
    foreground: float = 200.0
    background: float = 40.0
    residual_blur_px: float = 0.6
    noise_std: float = 2.0
    f_number: float = 2.9
    breathing: bool = False  # image scale v0/p (thin-lens chief ray) instead of f/p (pinhole)
    psf: Psf = "disc"  # render_disc's PSF; "aberrated" takes the blur's sign from the side of focus


def render_disc(
    width: int,
    height: int,
    center: tuple[float, float],
    radius_px: float,
    blur_px: float,
    *,
    residual_blur_px: float = 0.6,
    foreground: float = 200.0,
    background: float = 40.0,
    noise_std: float = 2.0,
    rng: np.random.Generator | None = None,
    psf: Psf = "disc",
    spherical_px: float = 2.5,
    sampled: bool = False,
) -> npt.NDArray[np.uint8]:
    """Render an anti-aliased disc blurred by a PSF of blur radius ``blur_px`` plus noise.

    ``psf``: a pillbox of radius ``|blur_px|``; a Gaussian of σ = |blur_px|/2 (same second
    moment); or ``aberrated``: rays ``t(ρ) = ρ (blur_px + s (ρ² − 2/3))`` of a uniform pupil
    (``blur_px`` signed: its sign picks the side of focus, ``s = spherical_px``).
    ``sampled``: one kernel, PSF ⊛ residual Gaussian sampled at pixel centres
    (:func:`defocus_kernel`: the second moment is exactly the PSF's on both sides of focus);
    otherwise (the closed-loop tests' renders) the PSF is integrated over pixels — a box of
    blur-dependent variance near focus — and the residual blur applied after.
    """
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    dist = np.hypot(xs - np.float32(center[0]), ys - np.float32(center[1]))
    coverage = np.clip(np.float32(radius_px) - dist + np.float32(0.5), 0.0, 1.0)
    img = (background + (foreground - background) * coverage).astype(np.float32)
    if sampled and residual_blur_px >= SAMPLED_KERNEL_MIN_SIGMA_PX:
        kernel = defocus_kernel(psf, blur_px, residual_blur_px, spherical_px)
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    else:  # the PSF integrated over pixels, then the residual blur
        if psf == "aberrated":
            kernel = defocus_kernel(psf, blur_px, 0.0, spherical_px)
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        elif psf == "gaussian" and abs(blur_px) > 0.05:
            img = cv2.GaussianBlur(img, (0, 0), 0.5 * abs(blur_px))
        elif psf == "disc" and abs(blur_px) > 0.3:
            img = cv2.filter2D(img, -1, _pillbox(abs(blur_px)), borderType=cv2.BORDER_REPLICATE)
        if residual_blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), residual_blur_px)
    if noise_std > 0:
        gen = rng if rng is not None else np.random.default_rng(0)
        img = img + gen.normal(0.0, noise_std, img.shape).astype(np.float32)
    return np.asarray(np.clip(np.rint(img), 0, 255), dtype=np.uint8)


def render_scene(
    scene: DiscScene,
    lens: Lens,
    focus_counts: int,
    position_m: tuple[float, float, float],
    rng: np.random.Generator | None = None,
) -> npt.NDArray[np.uint8]:
    """Render ``scene`` with the disc at camera-frame ``position_m`` and the lens at ``counts``."""
    x, y, z = position_m
    v0 = lens.v_from_counts(focus_counts)
    v = lens.v_from_depth(z)
    scale = v0 if scene.breathing else lens.focal_length_mm
    mag = scale / (z * MM_PER_M) / lens.pixel_pitch_mm  # px per mm in the target plane
    cx = scene.width / 2 + x * MM_PER_M * mag
    cy = scene.height / 2 + y * MM_PER_M * mag
    radius = scene.radius_m * MM_PER_M * mag
    blur = lens.blur_radius_px(v0, v, scene.f_number)
    if v0 < v:
        blur = -blur
    return render_disc(
        scene.width,
        scene.height,
        (cx, cy),
        radius,
        blur,
        residual_blur_px=scene.residual_blur_px,
        foreground=scene.foreground,
        background=scene.background,
        noise_std=scene.noise_std,
        rng=rng,
        psf=scene.psf,
    )


def synthetic_lens(
    focal_length_mm: float = 31.0, pixel_pitch_mm: float = 0.0056, f_number: float = 2.9
) -> Lens:
    """An EVI-D100-like focus table: counts 0x1000 (infinity) .. 0x8400 (about 1 m), nonlinear."""
    counts = np.linspace(0x1000, 0x8400, 30)
    # v - f grows convexly with counts, from 0 at infinity to the 1 m setting.
    v_near = focal_length_mm * 1000.0 / (1000.0 - focal_length_mm)
    u = (counts - counts[0]) / (counts[-1] - counts[0])
    v = focal_length_mm + (v_near - focal_length_mm) * (0.35 * u + 0.65 * u**2)
    return Lens(
        name="synthetic-evi-d100",
        focal_length_mm=focal_length_mm,
        pixel_pitch_mm=pixel_pitch_mm,
        focus_counts=tuple(int(c) for c in counts),
        focus_v_mm=tuple(float(x) for x in v),
        f_number=f_number,
    )


@dataclass(frozen=True, slots=True)
class StreamStep:
    """One frame of a closed-loop synthetic run with its truth."""

    frame: Frame
    tag: FrameTag
    truth_m: tuple[float, float, float]


class Planner:
    """What the closed loop asks of the estimator (implemented by ``Pipeline``)."""

    def plan_burst(self, current_counts: int) -> tuple[int, int, int]:
        """Three burst settings."""
        raise NotImplementedError

    def tracking_counts(self) -> int | None:
        """Best-focus setting for tracking frames."""
        raise NotImplementedError


def closed_loop(
    planner: Planner,
    scene: DiscScene,
    lens: Lens,
    trajectory: Trajectory,
    *,
    fps: float = 30.0,
    duration_s: float = 10.0,
    track_frames: int = 4,
    transit: bool = False,
    initial_counts: int | None = None,
    seed: int = 0,
) -> Iterator[StreamStep]:
    """A minimal lock-step scheduler: ``track_frames`` tracking frames, then a 3-frame burst.

    Focus moves are instantaneous unless ``transit``: then one transit frame (rendered at the
    midpoint setting, tagged without counts) precedes every change of setting. The caller must
    feed each yielded step to the planner's pipeline before asking for the next one.
    """
    rng = np.random.default_rng(seed)
    counts = initial_counts if initial_counts is not None else lens.counts_for_depth(4.0)
    index, burst_id = 0, 0
    dt = 1.0 / fps
    n_frames = int(duration_s * fps)

    def shot(c: int | None, role: str, burst: tuple[int, int] | None) -> StreamStep:
        t = index * dt
        pos = trajectory(t)
        render_counts = c if c is not None else counts
        img = render_scene(scene, lens, render_counts, pos, rng)
        tag = FrameTag(role=role, focus_counts=c, pan_deg=0.0, tilt_deg=0.0, burst=burst)  # type: ignore[arg-type]
        return StreamStep(Frame(index, t, img), tag, pos)

    while index < n_frames:
        for _ in range(track_frames):
            target = planner.tracking_counts()
            if target is not None and target != counts:
                if transit:
                    mid = (counts + target) // 2
                    prev, counts = counts, mid
                    yield shot(None, "transit", None)
                    index += 1
                    del prev
                counts = target
            yield shot(counts, "track", None)
            index += 1
        for slot, c in enumerate(planner.plan_burst(counts)):
            if transit and c != counts:
                counts = (counts + c) // 2
                yield shot(None, "transit", None)
                index += 1
            counts = c
            yield shot(counts, "burst", (burst_id, slot))
            index += 1
        burst_id += 1


def defocus_kernel(
    psf: Psf, blur_px: float, sigma0_px: float, spherical_px: float = 2.5
) -> npt.NDArray[np.float32]:
    """The defocus PSF ⊛ a Gaussian σ0, sampled at pixel centres (sums to 1).

    The PSF (disc of radius |b|; Gaussian σ = |b|/2; aberrated rays ``t(ρ) = ρ (b + s (ρ² −
    2/3))`` of a uniformly lit pupil, ``b`` signed) is built on a 9× finer grid, smoothed by σ0
    there, and *sampled*: with σ0 ≳ 0.5 px the sampled kernel keeps the second moment
    ``b²/4 (+ s²/72) + σ0²`` on both sides of focus (binning a sharp disc or a caustic ring into
    pixels instead adds a box variance that depends on the blur and on its sign).
    """
    fine = 9  # odd: a sub-sample sits on every pixel centre
    if psf == "gaussian":
        sigma = math.sqrt(sigma0_px**2 + 0.25 * blur_px**2)
        n = math.ceil(4 * sigma) + 1
        x = np.arange(-n, n + 1, dtype=np.float64)
        g = np.exp(-0.5 * (x / max(sigma, 1e-6)) ** 2)
        k = np.outer(g, g)
        return np.asarray(k / k.sum(), dtype=np.float32)
    if psf == "aberrated":
        d, sa = blur_px, spherical_px
        n_rho = max(64, math.ceil(4 * fine * (abs(d) + abs(sa))))
        u = (np.arange(n_rho) + 0.5) / n_rho  # ρ² uniform: equal-area zones
        t = np.sqrt(u) * (d + sa * (u - 2.0 / 3.0))
        r_max = float(np.abs(t).max())
    else:
        r_max = abs(blur_px)
    half = math.ceil(r_max + 4 * sigma0_px) + 1
    size = (2 * half + 1) * fine
    if psf == "aberrated":
        n_phi = max(64, math.ceil(4 * math.pi * r_max * fine))
        phi = (np.arange(n_phi) + 0.5) * (2 * math.pi / n_phi)
        x = (t[:, None] * np.cos(phi)[None, :]).ravel() * fine + size / 2
        y = (t[:, None] * np.sin(phi)[None, :]).ravel() * fine + size / 2
        density, _, _ = np.histogram2d(y, x, bins=size, range=[[0, size], [0, size]])
    else:
        axis = (np.arange(size) + 0.5) / fine - (half + 0.5)
        density = ((axis[:, None] ** 2 + axis[None, :] ** 2) <= r_max * r_max).astype(np.float64)
        if density.sum() == 0.0:
            density[size // 2, size // 2] = 1.0
    if sigma0_px > 0:
        density = cv2.GaussianBlur(
            density, (0, 0), sigma0_px * fine, borderType=cv2.BORDER_CONSTANT
        )
    k = density[fine // 2 :: fine, fine // 2 :: fine]
    return np.asarray(k / k.sum(), dtype=np.float32)


def _pillbox(radius: float) -> npt.NDArray[np.float32]:
    n = math.ceil(radius + 1)
    ys, xs = np.mgrid[-n : n + 1, -n : n + 1].astype(np.float32)
    k = np.clip(np.float32(radius) - np.hypot(xs, ys) + np.float32(0.5), 0.0, 1.0)
    return np.asarray(k / k.sum(), dtype=np.float32)
