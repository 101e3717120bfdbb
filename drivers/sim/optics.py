"""Physics of the simulated camera: thin lens, focus mechanics, defocus PSF, projection, sensor.

Written from first principles and deliberately independent of the estimator in ``dffd/`` (a
shared bug must not cancel out):

* Focal length and full-aperture f-number follow the zoom counts by tables; aperture
  ``D = f / N``.
* The focus motor's counts set the object distance the lens is focused at, as a focus power
  ``P`` (dioptres) that is a smooth nonlinear function of the counts; the lens-to-sensor distance
  follows from the thin-lens law ``1/f = 1/z + 1/v``: ``v0 = 1 / (1/f − P)``. So counts ↔ ``v0``
  is monotone and nonlinear; :meth:`Optics.lens_table_toml` writes it as the ground-truth
  calibration the estimator reads (``dffd/defaults/lenses/sim-evi-d100.toml``).
* A target at depth ``z`` is sharp at ``v = f z / (z − f)``; at ``v0`` its points spread into a
  blur circle of radius ``b = (D/2)|v0 − v|/v`` on the sensor (similar triangles through the
  aperture). PSF: a uniform disc of radius ``b/p`` pixels (default) or a Gaussian of the same
  second moment (σ = b/2), convolved with a residual Gaussian σ0 (aberrations, sensor).
* Perspective projection through the optical centre at the pan/tilt rotation centre; image
  scale ``f/p`` px (pinhole, design.md §3.4) or ``v0/p`` (chief ray of a thin lens, "breathing").
* Sensor: shot noise (variance ``signal/gain``), Gaussian read noise, rounding to 8 bits.

Rendering touches only the target's neighbourhood: the outline is filled on a supersampled
canvas (anti-aliased by area averaging), blurred with a cached PSF, optionally smeared along the
image motion during the exposure, and pasted onto a uniform background with per-pixel noise.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.config import LensConfig, SensorConfig, SimCameraConfig, load_sim_camera_config
from drivers.sim.resources import reference_camera_file

FloatArray = npt.NDArray[np.float64]
Image32 = npt.NDArray[np.float32]
Image8 = npt.NDArray[np.uint8]

MM_PER_M = 1000.0
# Focus-table spacing written to the lens file: 59 rows over 0x1000–0x8400. PCHIP through rows this
# dense reproduces the simulator's v0 to < 1e-5 mm (tests/test_sim_optics.py checks it).
LENS_TABLE_STEP_COUNTS = 0x200
LENS_TABLE_DECIMALS = 6  # 1e-6 mm of v ≈ 0.1 mm of depth at 10 m (dz = z² dv / f²)
# Blur radii are rounded to this before the PSF cache lookup: 0.02 px changes the peak edge
# gradient of a sharp edge by < 1 %, far below the noise of one focus-cost sample.
BLUR_QUANTUM_PX = 0.02
KERNEL_CACHE_SIZE = 1024
KERNEL_SUPERSAMPLE = 8  # sub-samples per pixel and axis when integrating the disc PSF
TARGET_SUPERSAMPLE = 4  # canvas sub-samples per pixel and axis for the target outline
MAX_CANVAS_PIXELS = 400_000  # supersampled canvas budget; larger targets use a coarser canvas
POLYGON_SHIFT_BITS = 8  # fixed-point fraction bits of vertex coordinates given to cv2.fillPoly
# cv2.fillPoly marks every canvas pixel the outline touches: measured +0.5 canvas pixel outward
# bias on discs of 10–60 px at 2×, 4× and 8× supersampling; the outline is inset by that much.
FILL_INSET_CANVAS_PX = 0.5
# Kernels wider than this are applied by FFT (cv2.dft); below it cv2.filter2D is faster. Measured
# on the dev machine (275×301 patch): 13×13 2.1 ms by filter2D (its own DFT path), 0.6 ms here.
FFT_KERNEL_MIN = 11
# Kernel spectra kept (≈ 0.5 MB each at a 360² transform): a steady defocus reuses its spectrum.
SPECTRUM_CACHE_SIZE = 32
MOTION_SAMPLES_PER_PX = 4  # points per pixel of smear when building a motion-blur kernel
MIN_MOTION_PX = 0.05  # below this the exposure-time smear is not modelled
_ZERO = np.zeros(1, dtype=np.float64)  # cv2.randn mean
_ONE = np.ones(1, dtype=np.float64)  # cv2.randn standard deviation


class Optics:
    """The lens and sensor geometry of one simulated camera (pure functions of its config)."""

    def __init__(self, sensor: SensorConfig, lens: LensConfig) -> None:
        self.sensor = sensor
        self.lens = lens
        self._zoom_counts = np.array([c for c, _ in lens.zoom_table], dtype=np.float64)
        self._zoom_f = np.array([f for _, f in lens.zoom_table], dtype=np.float64)
        self._fn_counts = np.array([c for c, _ in lens.f_number_table], dtype=np.float64)
        self._fn_values = np.array([n for _, n in lens.f_number_table], dtype=np.float64)

    @classmethod
    def from_config(cls, config: SimCameraConfig) -> Optics:
        """Optics of a whole simulated-camera config: the model ``[optics] model`` names."""
        if config.optics.model == "aberrated":
            # imported here: the aberrated model builds on this module
            from drivers.sim.optics_aberrated import AberratedOptics

            return AberratedOptics(config.sensor, config.lens, config.optics)
        return cls(config.sensor, config.lens)

    # -- geometry ----------------------------------------------------------------------------
    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.sensor.width_px, self.sensor.height_px

    @property
    def pixel_pitch_mm(self) -> float:
        """Sensor pixel pitch (square pixels)."""
        return self.sensor.pixel_pitch_mm

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """Optical axis in pixel coordinates (pixel centres at integers): the image centre."""
        return (self.sensor.width_px - 1) / 2.0, (self.sensor.height_px - 1) / 2.0

    def focal_length_mm(self, zoom_counts: float) -> float:
        """Focal length at a zoom position (piecewise linear in the zoom table)."""
        return float(np.interp(zoom_counts, self._zoom_counts, self._zoom_f))

    def f_number(self, zoom_counts: float) -> float:
        """Full-aperture f-number at a zoom position (iris assumed wide open)."""
        return float(np.interp(zoom_counts, self._fn_counts, self._fn_values))

    def aperture_mm(self, zoom_counts: float) -> float:
        """Entrance-pupil diameter D = f / N."""
        return self.focal_length_mm(zoom_counts) / self.f_number(zoom_counts)

    # -- focus -------------------------------------------------------------------------------
    def focus_power_dpt(self, focus_counts: float) -> float:
        """Object-side focus power P = 1/z_focus (dioptres) the lens is set to; 0 at infinity."""
        lens = self.lens
        span = lens.focus_near_counts - lens.focus_far_counts
        u = (focus_counts - lens.focus_far_counts) / span
        a = lens.focus_curvature
        return u * (1.0 + a * u) / (1.0 + a) / lens.near_focus_m

    def focus_distance_m(self, focus_counts: float) -> float:
        """Object distance in focus at these counts (``inf`` at the far end)."""
        power = self.focus_power_dpt(focus_counts)
        return math.inf if power <= 0.0 else 1.0 / power

    def focus_counts_for_depth(self, z_m: float) -> float:
        """The counts that focus the lens at depth ``z_m`` (inverse of :meth:`focus_power_dpt`)."""
        lens = self.lens
        power = 0.0 if math.isinf(z_m) else 1.0 / z_m
        s = power * lens.near_focus_m * (1.0 + lens.focus_curvature)
        a = lens.focus_curvature
        u = s if a == 0.0 else (-1.0 + math.sqrt(1.0 + 4.0 * a * s)) / (2.0 * a)
        return lens.focus_far_counts + u * (lens.focus_near_counts - lens.focus_far_counts)

    def lens_to_sensor_mm(self, focus_counts: float, zoom_counts: float) -> float:
        """v0: lens-to-sensor distance set by the focus motor (thin lens: 1/v0 = 1/f − P)."""
        f = self.focal_length_mm(zoom_counts)
        return 1.0 / (1.0 / f - self.focus_power_dpt(focus_counts) / MM_PER_M)

    def sharp_v_mm(self, z_m: float, zoom_counts: float) -> float:
        """v at which a plane at depth ``z_m`` is sharp: f z / (z − f)."""
        f = self.focal_length_mm(zoom_counts)
        z_mm = z_m * MM_PER_M
        if z_mm <= f:
            raise ValueError(f"depth {z_m} m is inside the focal length {f} mm: no real image")
        return f * z_mm / (z_mm - f)

    def blur_radius_px(self, v0_mm: float, v_mm: float, zoom_counts: float) -> float:
        """Blur-circle radius b/p in pixels: b = (D/2)|v0 − v| / v."""
        return 0.5 * self.aperture_mm(zoom_counts) * abs(v0_mm - v_mm) / v_mm / self.pixel_pitch_mm

    def scale_px(self, v0_mm: float, zoom_counts: float) -> float:
        """Image scale (pixels per unit of x/z): f/p, or v0/p when the lens breathes."""
        distance = v0_mm if self.lens.breathing else self.focal_length_mm(zoom_counts)
        return distance / self.pixel_pitch_mm

    def psf(self, blur_radius_px: float) -> Image32:
        """Normalised PSF for a blur-circle radius (with residual blur), cached."""
        quantised = round(blur_radius_px / BLUR_QUANTUM_PX) * BLUR_QUANTUM_PX
        return _psf_kernel(round(quantised, 6), self.lens.residual_blur_px, self.lens.psf)

    # -- the seams a second optics model overrides (drivers/sim/optics_aberrated.py) ---------
    def defocus_psf(self, v0_mm: float, v_mm: float, zoom_counts: float) -> Image32:
        """PSF of a point sharp at ``v_mm`` with the sensor at ``v0_mm`` (this lens: unsigned)."""
        return self.psf(self.blur_radius_px(v0_mm, v_mm, zoom_counts))

    def render_target(
        self,
        target: TargetImage,
        background_dn: float,
        kernel: Image32,
        motion_px: tuple[float, float],
    ) -> Patch | None:
        """The blurred target over a uniform ``background_dn`` (:func:`render_patch`)."""
        return render_patch(target, background_dn, kernel, motion_px, self.frame_size)

    def make_sensor(self) -> Sensor:
        """The sensor that exposes this lens's frames."""
        return Sensor(self.sensor)

    # -- ground-truth calibration file ------------------------------------------------------
    def lens_table(
        self, zoom_counts: float, step: int = LENS_TABLE_STEP_COUNTS
    ) -> list[tuple[int, float]]:
        """[(focus counts, v0 mm)] from the far to the near end, both ends included."""
        far, near = self.lens.focus_far_counts, self.lens.focus_near_counts
        counts = [*range(far, near, step), near]
        digits = LENS_TABLE_DECIMALS
        return [(c, round(self.lens_to_sensor_mm(c, zoom_counts), digits)) for c in counts]

    def lens_table_toml(self, zoom_counts: int) -> str:
        """The lens calibration file (docs/design.md §3 format) of this camera at a fixed zoom."""
        rows = self.lens_table(zoom_counts)
        width = LENS_TABLE_DECIMALS
        table = ",\n".join(f"    [{c}, {v:.{width}f}]" for c, v in rows)
        return (
            "# Ground-truth focus table of the simulated EVI-D100-like camera (design.md §3).\n"
            "# GENERATED from the reference camera (drivers/sim/data/sim-camera.toml) by\n"
            "#   python -m drivers.sim.optics --write dffd/defaults/lenses/sim-evi-d100.toml\n"
            "# Do not edit by hand; tests/test_sim_optics.py checks it against the simulator.\n"
            "\n"
            "[lens]\n"
            f'name = "{self.lens.name}"\n'
            f"focal_length_mm = {self.focal_length_mm(zoom_counts)!r}\n"
            f"pixel_pitch_mm = {self.pixel_pitch_mm!r}\n"
            f"f_number = {self.f_number(zoom_counts)!r}\n"
            f"zoom_counts = {zoom_counts}\n"
            "# focus counts -> lens-to-sensor distance v (mm); counts strictly increasing, "
            "v strictly monotone\n"
            f"focus_table = [\n{table},\n]\n"
        )

    def write_lens_table(self, path: str | Path, zoom_counts: int) -> None:
        """Write :meth:`lens_table_toml` to ``path``."""
        Path(path).write_text(self.lens_table_toml(zoom_counts), encoding="utf-8")


def world_from_camera(pan_deg: float, tilt_deg: float) -> FloatArray:
    """Rotation taking camera-frame vectors to the world frame (columns: camera axes in world).

    The world frame is the camera frame at pan = tilt = 0 (x right, y down, z forward); positive
    pan turns the optical axis to the right (+x), positive tilt turns it up (−y). The head pans
    about the world vertical, then tilts about its own horizontal axis.
    """
    p, t = math.radians(pan_deg), math.radians(tilt_deg)
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    x_axis = (cp, 0.0, -sp)  # image right: horizontal, perpendicular to the axis
    z_axis = (sp * ct, -st, cp * ct)  # optical axis
    y_axis = (sp * st, ct, cp * st)  # image down = z × x
    return np.array([x_axis, y_axis, z_axis], dtype=np.float64).T


def project(
    points_world: FloatArray,
    pan_deg: float,
    tilt_deg: float,
    scale_px: float,
    principal_px: tuple[float, float],
) -> tuple[FloatArray, FloatArray]:
    """Project world points (N×3, m): returns pixel coordinates (N×2) and camera-frame depths."""
    cam = np.asarray(points_world, dtype=np.float64) @ world_from_camera(pan_deg, tilt_deg)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = principal_px[0] + scale_px * cam[:, 0] / z
        v = principal_px[1] + scale_px * cam[:, 1] / z
    uv = np.stack((u, v), axis=1)
    return uv, z


@dataclass(frozen=True, slots=True)
class TargetImage:
    """What to draw at mid-exposure, in pixel coordinates (pixel centres at integers)."""

    outline_px: FloatArray  # N×2 convex outline, either orientation
    foreground_dn: float  # face brightness where there is no texture
    texture: Image32 | None = None  # target-plane texture in DN (rows run along +y)
    texture_corners_px: FloatArray | None = None  # where the texture's corners land (TL TR BR BL)
    texture_nearest: bool = False  # nearest-texel lookup (crisp ArUco cells)


@dataclass(frozen=True, slots=True)
class Patch:
    """A rendered, blurred neighbourhood of the target in DN (float) and where it sits."""

    image: Image32
    x0: int  # column of image[:, 0] in the frame (may be negative)
    y0: int
    # blurred coverage of the target (0–1), when a sensor composites the patch over a textured
    # background (the image was blended with a uniform background_dn)
    alpha: Image32 | None = None


@dataclass(frozen=True, slots=True)
class FrameView:
    """Where the camera looks during an exposure (what a textured background depends on)."""

    pan_deg: float
    tilt_deg: float
    v0_mm: float
    zoom_counts: float


def render_patch(
    target: TargetImage,
    background_dn: float,
    kernel: Image32,
    motion_px: tuple[float, float],
    frame_size: tuple[int, int],
) -> Patch | None:
    """Rasterise, blur and smear the target's neighbourhood; None if it misses the frame."""
    width, height = frame_size
    pts = target.outline_px
    if not np.all(np.isfinite(pts)):
        return None
    motion = _motion_kernel(*_bounded_motion(motion_px, frame_size))
    margin = kernel.shape[0] // 2 + (0 if motion is None else motion.shape[0] // 2) + 2
    x0 = max(math.floor(float(pts[:, 0].min())) - margin, -margin)
    y0 = max(math.floor(float(pts[:, 1].min())) - margin, -margin)
    x1 = min(math.ceil(float(pts[:, 0].max())) + margin + 1, width + margin)
    y1 = min(math.ceil(float(pts[:, 1].max())) + margin + 1, height + margin)
    if x1 <= max(x0, 0) or y1 <= max(y0, 0) or x0 >= width or y0 >= height:
        return None
    w, h = x1 - x0, y1 - y0
    # A texture is interpolated anyway; 2× keeps its edges exact (inset) at a quarter the cost.
    ss = TARGET_SUPERSAMPLE if target.texture is None else max(1, TARGET_SUPERSAMPLE // 2)
    while ss > 1 and w * h * ss * ss > MAX_CANVAS_PIXELS:
        ss //= 2
    # Canvas coordinates: pixel centre x ↦ (x − x0 + 0.5)·ss − 0.5.
    offset = np.array([x0, y0], dtype=np.float64)
    canvas_pts = (pts - offset + 0.5) * ss - 0.5
    mask = np.zeros((h * ss, w * ss), dtype=np.uint8)
    fixed = np.round(_inset_convex(canvas_pts, FILL_INSET_CANVAS_PX) * (1 << POLYGON_SHIFT_BITS))
    cv2.fillPoly(mask, [fixed.astype(np.int32)], 255, lineType=cv2.LINE_8, shift=POLYGON_SHIFT_BITS)
    if target.texture is None or target.texture_corners_px is None:
        coverage = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        image = background_dn + (target.foreground_dn - background_dn) / 255.0 * coverage
    else:
        tex = target.texture
        th, tw = tex.shape
        corners = [[-0.5, -0.5], [tw - 0.5, -0.5], [tw - 0.5, th - 0.5], [-0.5, th - 0.5]]
        src = np.array(corners, dtype=np.float32)
        dst = ((target.texture_corners_px - offset + 0.5) * ss - 0.5).astype(np.float32)
        homography = cv2.getPerspectiveTransform(src, dst)
        flags = cv2.INTER_NEAREST if target.texture_nearest else cv2.INTER_LINEAR
        warped = cv2.warpPerspective(
            tex, homography, (w * ss, h * ss), flags=flags, borderMode=cv2.BORDER_REPLICATE
        )
        fine = np.full(warped.shape, background_dn, dtype=np.float32)
        np.copyto(fine, warped, where=mask > 0)
        image = np.asarray(cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA), np.float32)
    blurred = _convolve(image, kernel)
    if motion is not None:
        blurred = _convolve(blurred, motion)
    return Patch(blurred, x0, y0)


def average_kernels(kernels: Sequence[Image32]) -> Image32:
    """Mean of centred kernels of odd sizes: the PSF of an exposure while the focus moves."""
    size = max(k.shape[0] for k in kernels)
    total = np.zeros((size, size), dtype=np.float32)
    for k in kernels:
        pad = (size - k.shape[0]) // 2
        total[pad : pad + k.shape[0], pad : pad + k.shape[1]] += k
    return np.asarray(total / np.float32(len(kernels)), dtype=np.float32)


class Sensor:
    """Turns a scene in DN into an 8-bit frame with shot and read noise; not thread-safe."""

    def __init__(self, config: SensorConfig) -> None:
        self.config = config
        shape = (config.height_px, config.width_px)
        self._noise = np.empty(shape, dtype=np.float32)
        self._frame = np.empty(shape, dtype=np.float32)

    def expose(
        self, background_dn: float, patch: Patch | None, seed: int, view: FrameView | None = None
    ) -> Image8:
        """A frame of uniform background plus the patch, with noise drawn from ``seed``.

        ``view`` is for sensors that composite over a textured background; unused here.
        """
        del view
        cfg = self.config
        # OpenCV's RNG is per thread; reseeding it here makes each frame's noise a pure function
        # of the seed, whatever thread renders it. cv2.randn is ~3× faster than numpy here.
        cv2.setRNGSeed(seed & 0x7FFFFFFF)
        cv2.randn(self._noise, _ZERO, _ONE)
        frame = self._frame
        np.multiply(self._noise, np.float32(self._sigma(background_dn)), out=frame)
        frame += np.float32(background_dn)
        if patch is not None:
            h, w = patch.image.shape
            fx0, fy0 = max(patch.x0, 0), max(patch.y0, 0)
            fx1, fy1 = min(patch.x0 + w, cfg.width_px), min(patch.y0 + h, cfg.height_px)
            if fx1 > fx0 and fy1 > fy0:
                rows = slice(fy0 - patch.y0, fy1 - patch.y0)
                signal = patch.image[rows, fx0 - patch.x0 : fx1 - patch.x0]
                sigma = self._sigma_map(signal)
                frame[fy0:fy1, fx0:fx1] = signal + sigma * self._noise[fy0:fy1, fx0:fx1]
        np.maximum(frame, 0.0, out=frame)
        return np.asarray(cv2.convertScaleAbs(frame), dtype=np.uint8)  # rounds, saturates at 255

    def _sigma(self, dn: float) -> float:
        shot = max(dn, 0.0) / self.config.gain_e_per_dn if self.config.gain_e_per_dn > 0 else 0.0
        return math.sqrt(shot + self.config.read_noise_dn**2)

    def _sigma_map(self, signal: Image32) -> Image32:
        read2 = np.float32(self.config.read_noise_dn**2)
        if self.config.gain_e_per_dn <= 0:
            return np.full_like(signal, np.sqrt(read2))
        shot = np.maximum(signal, 0.0) / np.float32(self.config.gain_e_per_dn)
        return np.asarray(np.sqrt(shot + read2), dtype=np.float32)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.optics --write FILE``: regenerate the ground-truth lens table."""
    parser = argparse.ArgumentParser(
        prog="python -m drivers.sim.optics",
        description="Write the simulated camera's ground-truth focus table (lens TOML).",
    )
    parser.add_argument(
        "--config", help="simulated camera TOML (default: the reference camera, package data)"
    )
    parser.add_argument("--write", metavar="FILE", help="output lens file (default: stdout)")
    args = parser.parse_args(argv)
    config = load_sim_camera_config(args.config or reference_camera_file())
    optics = Optics.from_config(config)
    if args.write:
        optics.write_lens_table(args.write, config.zoom_counts)
    else:
        sys.stdout.write(optics.lens_table_toml(config.zoom_counts))
    return 0


# -- private helpers ------------------------------------------------------------------------


@functools.lru_cache(maxsize=KERNEL_CACHE_SIZE)
def _psf_kernel(radius_px: float, sigma0_px: float, kind: str) -> Image32:
    if kind == "gaussian":
        sigma = math.hypot(sigma0_px, 0.5 * radius_px)  # a uniform disc has σ = b/2 per axis
        if sigma < 1e-3:
            return np.ones((1, 1), dtype=np.float32)
        half = math.ceil(3.0 * sigma) + 1
        x = np.arange(-half, half + 1, dtype=np.float64)
        g = np.exp(-0.5 * (x / sigma) ** 2)
        kernel = np.outer(g, g)
    else:
        half = math.ceil(radius_px + 3.0 * sigma0_px) + 1
        n = KERNEL_SUPERSAMPLE
        sub = (np.arange(n) + 0.5) / n - 0.5
        axis = (np.arange(-half, half + 1)[:, None] + sub[None, :]).ravel()
        inside = (axis[:, None] ** 2 + axis[None, :] ** 2) <= radius_px**2
        size = 2 * half + 1
        kernel = inside.reshape(size, n, size, n).mean(axis=(1, 3))
        if kernel.sum() == 0.0:  # radius below the sub-sample spacing: a point
            kernel[half, half] = 1.0
        if sigma0_px > 0.0:
            kernel = cv2.GaussianBlur(kernel, (0, 0), sigma0_px, borderType=cv2.BORDER_CONSTANT)
    normalised = np.asarray(kernel / kernel.sum(), dtype=np.float32)
    normalised.setflags(write=False)
    return normalised


def _convolve(image: Image32, kernel: Image32) -> Image32:
    """Filter with a point-symmetric kernel, replicating the border (same size as ``image``)."""
    if kernel.shape[0] < FFT_KERNEL_MIN:
        out = cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        return np.asarray(out, dtype=np.float32)
    half = kernel.shape[0] // 2
    padded = cv2.copyMakeBorder(image, half, half, half, half, cv2.BORDER_REPLICATE)
    rows, cols = cv2.getOptimalDFTSize(padded.shape[0]), cv2.getOptimalDFTSize(padded.shape[1])
    canvas = np.zeros((rows, cols), dtype=np.float32)
    canvas[: padded.shape[0], : padded.shape[1]] = padded
    k = np.ascontiguousarray(kernel, dtype=np.float32)
    spectrum = cv2.mulSpectrums(cv2.dft(canvas), _kernel_spectrum(k.tobytes(), half, rows, cols), 0)
    full = cv2.idft(spectrum, flags=cv2.DFT_SCALE | cv2.DFT_REAL_OUTPUT)
    h, w = image.shape
    return np.ascontiguousarray(full[half : half + h, half : half + w], dtype=np.float32)


@functools.lru_cache(maxsize=SPECTRUM_CACHE_SIZE)
def _kernel_spectrum(kernel_bytes: bytes, half: int, rows: int, cols: int) -> Image32:
    # Kernel centred on the origin (wrapped): output pixel i sums inputs i − k, k ∈ [−half, half],
    # which never wrap for the rows and columns of the original image (they start at ``half``).
    size = 2 * half + 1
    k = np.frombuffer(kernel_bytes, dtype=np.float32).reshape(size, size)
    wrapped = np.zeros((rows, cols), dtype=np.float32)
    wrapped[: half + 1, : half + 1] = k[half:, half:]
    wrapped[: half + 1, cols - half :] = k[half:, :half]
    wrapped[rows - half :, : half + 1] = k[:half, half:]
    wrapped[rows - half :, cols - half :] = k[:half, :half]
    spectrum = np.asarray(cv2.dft(wrapped), dtype=np.float32)
    spectrum.setflags(write=False)
    return spectrum


def _bounded_motion(
    motion_px: tuple[float, float], frame_size: tuple[int, int]
) -> tuple[float, float]:
    """The smear, cut to the frame's diagonal (same direction).

    A longer one (the head slewing during the exposure, e.g. a search sweep, with an end of the
    exposure projected far outside the image) spreads the target's light below the noise anyway,
    while its kernel grows as the square of its length: 21,469 px asked for 3.4 GiB.
    """
    dx, dy = motion_px
    length = math.hypot(dx, dy)
    limit = math.hypot(*frame_size)
    if not math.isfinite(length):
        return (0.0, 0.0)
    if length <= limit:
        return (dx, dy)
    return (dx * limit / length, dy * limit / length)


def _motion_kernel(dx: float, dy: float) -> Image32 | None:
    """Box blur along the segment (−d/2, +d/2): the image motion during the exposure."""
    length = math.hypot(dx, dy)
    if length < MIN_MOTION_PX:
        return None
    half = math.ceil(max(abs(dx), abs(dy)) / 2.0) + 1
    size = 2 * half + 1
    n = max(2, math.ceil(length * MOTION_SAMPLES_PER_PX) + 1)
    s = np.linspace(-0.5, 0.5, n)
    xs, ys = half + s * dx, half + s * dy
    ix, iy = np.floor(xs).astype(np.int64), np.floor(ys).astype(np.int64)
    fx, fy = xs - ix, ys - iy
    kernel = np.zeros((size, size), dtype=np.float64)
    np.add.at(kernel, (iy, ix), (1 - fx) * (1 - fy))
    np.add.at(kernel, (iy, ix + 1), fx * (1 - fy))
    np.add.at(kernel, (iy + 1, ix), (1 - fx) * fy)
    np.add.at(kernel, (iy + 1, ix + 1), fx * fy)
    return np.asarray(kernel / kernel.sum(), dtype=np.float32)


def _inset_convex(points: FloatArray, delta: float) -> FloatArray:
    """Move every edge of a convex polygon inwards by ``delta`` (mitred vertices)."""
    p = np.asarray(points, dtype=np.float64)
    nxt = np.roll(p, -1, axis=0)
    signed_area = 0.5 * float(np.sum(p[:, 0] * nxt[:, 1] - nxt[:, 0] * p[:, 1]))
    if delta == 0.0 or abs(signed_area) < 1e-9:
        return p
    edges = nxt - p
    lengths = np.hypot(edges[:, 0], edges[:, 1])
    lengths[lengths == 0.0] = 1.0
    # Inward normal of each edge: left of the direction for counter-clockwise (positive area).
    sign = 1.0 if signed_area > 0 else -1.0
    normals = sign * np.stack((-edges[:, 1], edges[:, 0]), axis=1) / lengths[:, None]
    prev_normals = np.roll(normals, 1, axis=0)
    bisector = normals + prev_normals
    cos_term = 1.0 + np.sum(normals * prev_normals, axis=1)
    cos_term[cos_term < 1e-6] = 1e-6
    return np.asarray(p + delta * bisector / cos_term[:, None], dtype=np.float64)


if __name__ == "__main__":
    sys.exit(main())
