"""The second optics model (``[optics] model = "aberrated"``): PSF, focus cam, wall, outline, noise.

Measurements are written independently of the renderer: moments of the kernels by summation,
edge sharpness from Sobel gradients of the rendered frames, sizes from OpenCV contours.
"""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from drivers.sim.config import (
    SimCameraConfig,
    SimConfigError,
    TargetConfig,
    TrajectoryConfig,
    WorldConfig,
    with_overrides,
)
from drivers.sim.optics import Optics
from drivers.sim.optics_aberrated import AberratedOptics
from drivers.sim.outline import irregular_unit_outline
from drivers.sim.source import SimFrameSource, camera_state_for
from drivers.sim.virtual_clock import VirtualClock
from drivers.sim.world import World, boundary_samples, make_shape, rms_radius

CLOCK_START_S = 100.0  # virtual time a scene starts at


def _config(**overrides: object) -> SimCameraConfig:
    base = {"optics.model": "aberrated", "lens.focus_jitter_counts": 0.0}
    return with_overrides(SimCameraConfig(), {**base, **overrides})


def _source(config: SimCameraConfig) -> tuple[SimFrameSource, VirtualClock]:
    clock = VirtualClock(CLOCK_START_S)
    state = camera_state_for(config, clock=clock)
    return SimFrameSource.from_config(config, state), clock


def _moments(kernel: np.ndarray) -> tuple[float, float, float]:
    k = kernel.astype(np.float64)
    x = np.arange(k.shape[0]) - (k.shape[0] - 1) / 2
    total = float(k.sum())
    return total, float((k * x[None, :] ** 2).sum() / total), float((k * x[:, None]).sum() / total)


def _focus_on(source: SimFrameSource, clock: VirtualClock, defocus_px: float, z: float) -> None:
    optics = source.optics
    assert isinstance(optics, AberratedOptics)
    zoom = source.state.snapshot(clock()).zoom_counts
    v = optics.sharp_v_mm(z, zoom)
    v0 = v + defocus_px / optics.signed_defocus_px(v + 1.0, v, zoom)
    f = optics.focal_length_mm(zoom)
    power = (1.0 / f - 1.0 / v0) * 1000.0
    source.state.focus.jump(optics.focus_counts_for_depth(1.0 / power), clock())


def test_default_model_is_the_reference_and_the_config_selects_the_aberrated_one() -> None:
    assert SimCameraConfig().optics.model == "reference"
    assert type(Optics.from_config(SimCameraConfig())) is Optics
    optics = Optics.from_config(_config())
    assert isinstance(optics, AberratedOptics)
    assert optics.lens.name == "sim-aberrated"
    with pytest.raises(SimConfigError, match="monotone"):
        _config(**{"optics.focus_exponent": 4.0, "optics.focus_ripple": 0.2})


@pytest.mark.parametrize("defocus", [-12.0, -4.0, -1.0, 0.0, 1.0, 4.0, 12.0])
def test_psf_integrates_to_one_with_the_second_moment_of_the_ray_model(defocus: float) -> None:
    optics = Optics.from_config(_config())
    assert isinstance(optics, AberratedOptics)
    kernel = optics.psf_signed(defocus)
    total, m2, m1 = _moments(kernel)
    assert total == pytest.approx(1.0, abs=1e-5)
    assert abs(m1) < 1e-6  # centred
    # per axis: d²/4 + s²/72 + σ0², plus the pixel aperture's 1/12 (1 % and 0.02 px²)
    assert m2 == pytest.approx(
        optics.psf_second_moment_px2(defocus) + 1.0 / 12.0, rel=0.01, abs=0.02
    )


def test_psf_shape_depends_on_the_side_of_focus() -> None:
    optics = Optics.from_config(_config())
    assert isinstance(optics, AberratedOptics)
    near, far = optics.psf_signed(-4.0), optics.psf_signed(4.0)
    assert near.shape == far.shape or abs(near.shape[0] - far.shape[0]) <= 4
    c_near, c_far = near.shape[0] // 2, far.shape[0] // 2
    # a caustic ring on one side (dim centre), a peaked disc on the other
    assert near[c_near, c_near] < 0.5 * near.max()
    assert far[c_far, c_far] == pytest.approx(far.max())
    assert _moments(near)[1] == pytest.approx(_moments(far)[1], rel=0.01)


def test_focus_curve_is_monotone_inverts_and_differs_from_the_reference() -> None:
    config = _config()
    ab, ref = Optics.from_config(config), Optics.from_config(SimCameraConfig())
    zoom = config.zoom_counts
    counts = np.linspace(config.lens.focus_far_counts, config.lens.focus_near_counts, 400)
    v0 = np.array([ab.lens_to_sensor_mm(c, zoom) for c in counts])
    assert np.all(np.diff(v0) > 0)
    for z in (1.5, 3.0, 7.0, 12.0):
        c = ab.focus_counts_for_depth(z)
        assert ab.focus_distance_m(c) == pytest.approx(z, rel=1e-9)
    v_ref = np.array([ref.lens_to_sensor_mm(c, zoom) for c in counts])
    assert np.max(np.abs(v0 - v_ref)) > 0.05  # mm: another lens, another table
    rows = ab.lens_table(zoom)
    assert all(b[1] > a[1] for a, b in itertools.pairwise(rows))
    assert 'name = "sim-aberrated"' in ab.lens_table_toml(zoom)


def test_renders_are_reproducible_from_the_seed() -> None:
    frames = []
    for seed in (7, 7, 8):
        source, clock = _source(_config(seed=seed, **{"world.target.shape": "irregular"}))
        _focus_on(source, clock, 2.0, 5.0)
        frames.append(source.render_frame(3).image)
    assert np.array_equal(frames[0], frames[1])
    assert not np.array_equal(frames[0], frames[2])


def test_blur_grows_with_defocus_on_both_sides() -> None:
    config = _config(
        **{
            "sensor.read_noise_dn": 0.0,
            "sensor.gain_e_per_dn": 0.0,
            "optics.background_contrast_dn": 0.0,
            "world.target.size_m": 0.1,  # r ≈ 155 px at 4 m: a nearly straight edge
            "world.trajectory.position_m": (0.0, 0.0, 4.0),
        }
    )
    source, clock = _source(config)

    def edge_spread(defocus: float) -> float:
        """Variance of the edge-derivative profile across the target's left edge."""
        _focus_on(source, clock, defocus, 4.0)
        img, truth = source.render(clock())
        x_edge = round(truth.centre_px[0] - truth.r_px)
        rows = img[236:245, x_edge - 30 : x_edge + 31].astype(np.float64).mean(axis=0)
        deriv = np.diff(rows)
        x = np.arange(len(deriv), dtype=np.float64)
        mean = float((x * deriv).sum() / deriv.sum())
        return float(((x - mean) ** 2 * deriv).sum() / deriv.sum())

    for side in (1.0, -1.0):
        variances = [edge_spread(side * b) for b in (0.0, 1.0, 2.0, 4.0, 6.0, 9.0)]
        assert np.all(np.diff(variances) > 0), (side, variances)


def test_background_wall_is_textured_blurred_by_its_defocus_and_fixed_in_the_world() -> None:
    config = _config(**{"sensor.read_noise_dn": 0.0, "sensor.gain_e_per_dn": 0.0})
    source, clock = _source(config)
    _focus_on(source, clock, 0.0, config.optics.background_depth_m)  # wall in focus
    sharp = source.render(clock())[0].astype(np.float32)
    corner = (slice(0, 120), slice(0, 160))  # away from the target at the centre
    assert sharp[corner].std() > 1.5
    _focus_on(source, clock, 0.0, 2.0)  # focused near: the wall blurs
    blurred = source.render(clock())[0].astype(np.float32)
    assert blurred[corner].std() < 0.7 * sharp[corner].std()
    # pan right by ~10 px: the wall moves left by as much
    _focus_on(source, clock, 0.0, config.optics.background_depth_m)
    scale = config.lens.zoom_table[-1][1] / config.sensor.pixel_pitch_mm
    source.state.pan.jump(math.degrees(10.0 / scale), clock())
    panned = source.render(clock())[0].astype(np.float32)
    assert np.allclose(panned[0:120, 0:150], sharp[0:120, 10:160], atol=1.01)


def test_noise_is_shot_plus_read() -> None:
    config = _config(
        **{"optics.background_contrast_dn": 0.0, "world.trajectory.position_m": (5.0, 0.0, 5.0)}
    )
    source, _ = _source(config)
    img = source.render_frame(1).image.astype(np.float64)
    expected = math.sqrt(
        config.world.background_dn / config.sensor.gain_e_per_dn + config.sensor.read_noise_dn**2
    )
    assert img.std() == pytest.approx(expected, rel=0.05)
    assert img.mean() == pytest.approx(config.world.background_dn, abs=0.1)


def test_irregular_outline_is_non_convex_star_shaped_sized_and_rotates() -> None:
    unit = irregular_unit_outline(3)
    rho = np.hypot(unit[:, 0], unit[:, 1])
    assert rho.min() > 0.8
    hull = cv2.convexHull(unit.astype(np.float32))
    assert cv2.contourArea(hull) > 1.01 * cv2.contourArea(unit.astype(np.float32))  # not convex
    assert not np.allclose(unit, irregular_unit_outline(4))
    shape = make_shape(TargetConfig(shape="irregular", size_m=0.05, texture_seed=3))
    assert rms_radius(boundary_samples(shape.outline_m)) == pytest.approx(0.05, rel=1e-6)
    world = World.from_config(
        WorldConfig(
            target=TargetConfig(shape="irregular", rotation_dps=90.0),
            trajectory=TrajectoryConfig(kind="static", position_m=(0.0, 0.0, 4.0)),
        )
    )
    a, b = world.outline_world(world.pose(0.0)), world.outline_world(world.pose(0.5))
    assert not np.allclose(a, b)


def test_render_speed_is_close_to_the_reference() -> None:
    # not a timing assertion (shared CI): both renderers do the same kind of work per frame; the
    # measured figures are in docs/estimation.md. Here: a moving, spinning target renders.
    config = _config(
        **{
            "world.target.shape": "irregular",
            "world.target.rotation_dps": 30.0,
            "world.trajectory.kind": "linear",
            "world.trajectory.position_m": (0.0, 0.0, 6.0),
            "world.trajectory.end_m": (0.2, 0.0, 3.0),
            "world.trajectory.speed_mps": 1.0,
        }
    )
    source, clock = _source(config)
    _focus_on(source, clock, 0.0, 4.5)
    for i in range(5):
        truth_img = source.render_frame(i).image
        truth = source.truth_for(i)
        assert truth is not None
        assert truth.in_view
        assert truth_img.shape == (480, 640)
