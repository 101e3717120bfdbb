"""Physics of the simulated camera: image size, focus cost, blur, pan/tilt, truth, lens file.

Measurements here are written independently of the renderer: sizes come from OpenCV contours of
the rendered frames, focus costs from Sobel gradients along lines normal to the boundary.
"""

from __future__ import annotations

import asyncio
import math
import tomllib

import cv2
import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from dffd.resources import lens_table
from drivers.frames import Frame, FrameSource, FrameSourceError
from drivers.sim.config import (
    CaptureConfig,
    SimCameraConfig,
    TargetConfig,
    TrajectoryConfig,
    WorldConfig,
    load_sim_camera_config,
    with_overrides,
)
from drivers.sim.optics import Optics, TargetImage, render_patch, world_from_camera
from drivers.sim.resources import reference_camera_file
from drivers.sim.source import SimFrameSource, camera_state_for
from drivers.sim.state import CameraState
from drivers.sim.virtual_clock import VirtualClock
from drivers.sim.world import World, boundary_samples, make_shape, make_trajectory, rms_radius

SIM_CONFIG = reference_camera_file()
LENS_FILE = lens_table("sim-evi-d100")
CLOCK_START_S = 100.0  # virtual time a scene starts at
FRAME_TIMEOUT_S = 5.0  # generous bound on a live frame at 30 fps (3 periods + latency ≈ 0.15 s)


@pytest.fixture(scope="module")
def reference() -> SimCameraConfig:
    return load_sim_camera_config(SIM_CONFIG)


def _quiet(config: SimCameraConfig) -> SimCameraConfig:
    return with_overrides(
        config,
        {"sensor.read_noise_dn": 0.0, "sensor.gain_e_per_dn": 0.0, "lens.focus_jitter_counts": 0.0},
    )


def _scene(
    config: SimCameraConfig,
    world: WorldConfig,
    clock: VirtualClock | None = None,
) -> tuple[SimFrameSource, CameraState, VirtualClock]:
    clock = clock or VirtualClock(CLOCK_START_S)
    state = camera_state_for(config, clock=clock)
    source = SimFrameSource.from_config(config, state, World.from_config(world))
    return source, state, clock


def _static(z: float, x: float = 0.0, y: float = 0.0, **target: object) -> WorldConfig:
    return WorldConfig(
        target=TargetConfig.model_validate(target),
        trajectory=TrajectoryConfig(kind="static", position_m=(x, y, z)),
    )


def _focus_at(state: CameraState, optics: Optics, z: float) -> None:
    state.focus.jump(optics.focus_counts_for_depth(z), state.now())


def _counts_for_v0(optics: Optics, v0_mm: float, zoom: float) -> float:
    f = optics.focal_length_mm(zoom)
    power_dpt = (1.0 / f - 1.0 / v0_mm) * 1000.0
    return optics.focus_counts_for_depth(1.0 / power_dpt)


def _contour_r(image: np.ndarray, background: float, foreground: float) -> tuple[float, np.ndarray]:
    """sqrt(tr Σ) of the target boundary from OpenCV contours on an 8× upsampled image."""
    up = 8
    big = cv2.resize(image.astype(np.float32), None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR)
    binary = (big > 0.5 * (background + foreground)).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
    pts = (contour + 0.5) / up - 0.5  # back to pixel-centre coordinates of the frame
    uniform = boundary_samples(pts, 2048)
    return rms_radius(uniform), uniform.mean(axis=0)


def _focus_cost(
    image: np.ndarray, centre: tuple[float, float], radius: float, half_width: float
) -> float:
    """design.md §3.2: inverse mean of squared max gradient magnitude along 64 boundary normals."""
    img = image.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag2 = gx * gx + gy * gy
    angles = np.linspace(0.0, 2.0 * math.pi, 64, endpoint=False)
    s = np.arange(radius - half_width, radius + half_width, 0.25)
    map_x = (centre[0] + np.cos(angles)[:, None] * s[None, :]).astype(np.float32)
    map_y = (centre[1] + np.sin(angles)[:, None] * s[None, :]).astype(np.float32)
    samples = cv2.remap(mag2, map_x, map_y, interpolation=cv2.INTER_LINEAR)
    return 1.0 / float(np.mean(samples.max(axis=1)))


# -- reference camera -------------------------------------------------------------------------


def test_reference_camera_sees_the_paper_target_at_10m_with_at_least_20px(reference) -> None:
    optics = Optics.from_config(reference)
    f = optics.focal_length_mm(reference.zoom_counts)
    r_px = f * 0.03576 / 10.0 / optics.pixel_pitch_mm
    assert r_px >= 20.0
    assert reference.sensor.width_px == 640
    assert reference.sensor.height_px == 480
    assert reference.capture.fps == 30.0
    assert 2.0 <= optics.f_number(reference.zoom_counts) <= 3.5


def test_every_reference_parameter_is_commented() -> None:
    previous = ""
    for line in SIM_CONFIG.read_text(encoding="utf-8").splitlines():
        stripped = line.strip()
        if "=" in stripped and not stripped.startswith("#"):
            # a comment on the line, or a comment block right above it
            assert "#" in stripped or previous.startswith("#"), f"uncommented: {line}"
        previous = stripped


# -- image size -------------------------------------------------------------------------------


@pytest.mark.parametrize("z", [1.5, 3.0, 6.0, 10.0])
def test_rendered_disc_r_matches_f_R_over_z_within_1_percent(reference, z: float) -> None:
    source, state, _ = _scene(reference, _static(z))
    _focus_at(state, source.optics, z)
    frame = source.render_frame(0)
    truth = source.truth_for(0)
    assert truth is not None
    r_meas, centre = _contour_r(frame.image, 40.0, 200.0)
    f_px = source.optics.focal_length_mm(reference.zoom_counts) / source.optics.pixel_pitch_mm
    expected = f_px * 0.03576 / z
    assert r_meas == pytest.approx(expected, rel=0.01)
    assert truth.r_px == pytest.approx(expected, rel=1e-3)
    assert centre == pytest.approx(truth.centroid_px, abs=0.1)


@pytest.mark.parametrize("roll", [0.0, 17.0, 45.0])
def test_polygon_r_is_rotation_invariant_and_matches_f_R_over_z(reference, roll: float) -> None:
    source, state, _ = _scene(reference, _static(3.0, shape="polygon", sides=5, roll_deg=roll))
    _focus_at(state, source.optics, 3.0)
    r_meas, _ = _contour_r(source.render_frame(0).image, 40.0, 200.0)
    f_px = source.optics.focal_length_mm(reference.zoom_counts) / source.optics.pixel_pitch_mm
    assert r_meas == pytest.approx(f_px * 0.03576 / 3.0, rel=0.01)


def test_breathing_lens_scales_the_image_by_v0_over_f(reference) -> None:
    config = with_overrides(reference, {"lens.breathing": True})
    source, state, _ = _scene(config, _static(1.5))
    _focus_at(state, source.optics, 1.5)
    source.render_frame(0)
    truth = source.truth_for(0)
    assert truth is not None
    assert truth.r_px == pytest.approx(
        truth.v0_mm / source.optics.pixel_pitch_mm * 0.03576 / 1.5, rel=1e-3
    )
    assert truth.v0_mm / truth.focal_length_mm > 1.015  # the 1.5 % that the pinhole ignores


@pytest.mark.parametrize("shape", ["disc", "polygon", "textured", "aruco"])
def test_every_shape_has_the_configured_size(shape: str) -> None:
    target = make_shape(TargetConfig(shape=shape, size_m=0.05))
    assert rms_radius(target.boundary_m) == pytest.approx(0.05, rel=1e-3)


# -- focus ------------------------------------------------------------------------------------


def _sweep(config: SimCameraConfig, z: float, dv_mm: np.ndarray) -> tuple[np.ndarray, float, list]:
    source, state, clock = _scene(config, _static(z))
    optics = source.optics
    zoom = config.zoom_counts
    v_true = optics.sharp_v_mm(z, zoom)
    costs, truths = [], []
    for i, dv in enumerate(dv_mm):
        state.focus.jump(_counts_for_v0(optics, v_true + dv, zoom), clock())
        frame = source.render_frame(i)
        truth = source.truth_for(i)
        assert truth is not None
        truths.append(truth)
        costs.append(_focus_cost(frame.image, truth.centroid_px, truth.r_px, 8.0))
    return np.array(costs), v_true, truths


@pytest.mark.parametrize(
    ("z", "noisy", "shift"),
    [(2.0, False, 0.3), (4.0, False, -0.5), (4.0, True, 0.3), (8.0, True, -0.5), (10.0, True, 0.3)],
)
def test_focus_cost_is_a_parabola_with_its_vertex_at_the_true_v(reference, z, noisy, shift) -> None:
    config = reference if noisy else _quiet(reference)
    optics = Optics.from_config(config)
    # Sweep ±4 px of blur around a centre deliberately off the sharp setting (a symmetric sweep
    # would put the vertex at the truth by symmetry alone).
    v_true = optics.sharp_v_mm(z, config.zoom_counts)
    span = 4.0 / optics.blur_radius_px(v_true + 1.0, v_true, config.zoom_counts)
    dv = np.linspace(-span, span, 15) + shift * span
    costs, v_true, truths = _sweep(config, z, dv)
    v0 = np.array([t.v0_mm for t in truths])
    alpha, beta, gamma = np.polyfit(v0, costs, 2)
    assert alpha > 0
    vertex = -beta / (2 * alpha)
    residual = costs - np.polyval([alpha, beta, gamma], v0)
    r2 = 1.0 - np.sum(residual**2) / np.sum((costs - costs.mean()) ** 2)
    assert r2 > 0.99
    # Vertex within 2 % of the sweep's half-width of the truth (≈ 0.08 px of blur); measured
    # ≤ 1.1 %: the disc ⊛ Gaussian PSF makes the cost only nearly parabolic.
    assert abs(vertex - v_true) < 0.02 * span
    f = optics.focal_length_mm(config.zoom_counts)
    z_from_vertex = f * vertex / (vertex - f) / 1000.0
    assert z_from_vertex == pytest.approx(z, rel=0.01)


def test_blur_grows_monotonically_with_defocus_on_both_sides(reference) -> None:
    config = _quiet(reference)
    optics = Optics.from_config(config)
    z = 3.0
    v_true = optics.sharp_v_mm(z, config.zoom_counts)
    step = 1.0 / optics.blur_radius_px(v_true + 1.0, v_true, config.zoom_counts)  # 1 px of blur
    offsets = np.arange(0, 7) * step
    for side in (1.0, -1.0):
        costs, _, truths = _sweep(config, z, side * offsets)
        assert np.all(np.diff(costs) > 0), costs
        assert np.all(np.diff([t.blur_radius_px for t in truths]) > 0)


def test_psf_is_a_normalised_disc_of_the_blur_radius(reference) -> None:
    optics = Optics.from_config(_quiet(with_overrides(reference, {"lens.residual_blur_px": 0.0})))
    kernel = optics.psf(6.0)
    assert kernel.sum() == pytest.approx(1.0, abs=1e-5)
    c = kernel.shape[0] // 2
    assert kernel[c, c] == pytest.approx(1.0 / (math.pi * 36.0), rel=0.02)
    assert kernel[c, c + 7] == 0.0
    assert kernel is optics.psf(6.001)  # cached (quantised radius)


# -- pan / tilt -------------------------------------------------------------------------------


def _centroid(image: np.ndarray) -> tuple[float, float]:
    weights = np.clip(image.astype(np.float64) - 120.0, 0, None)
    m = cv2.moments(weights.astype(np.float32))
    return m["m10"] / m["m00"], m["m01"] / m["m00"]


def test_pan_right_moves_the_target_left_and_tilt_up_moves_it_down(reference) -> None:
    config = _quiet(reference)
    source, state, clock = _scene(config, _static(5.0))
    _focus_at(state, source.optics, 5.0)
    f_px = source.optics.focal_length_mm(config.zoom_counts) / source.optics.pixel_pitch_mm
    u0, v0 = _centroid(source.render_frame(0).image)
    assert (u0, v0) == pytest.approx(source.optics.principal_point_px, abs=0.05)

    state.pan.jump(1.0, clock())
    u1, v1 = _centroid(source.render_frame(1).image)
    assert u1 - u0 == pytest.approx(-f_px * math.tan(math.radians(1.0)), rel=0.01)
    assert v1 == pytest.approx(v0, abs=0.05)

    state.pan.jump(0.0, clock())
    state.tilt.jump(1.0, clock())
    u2, v2 = _centroid(source.render_frame(2).image)
    assert v2 - v0 == pytest.approx(f_px * math.tan(math.radians(1.0)), rel=0.01)
    assert u2 == pytest.approx(u0, abs=0.05)
    truth = source.truth_for(2)
    assert truth is not None
    assert truth.centroid_px == pytest.approx((u2, v2), abs=0.05)


def test_world_from_camera_is_a_rotation_with_the_documented_axes() -> None:
    r = world_from_camera(30.0, 10.0)
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    axis = r[:, 2]
    assert axis[0] > 0
    assert axis[1] < 0


# -- truth ------------------------------------------------------------------------------------


def test_truth_is_consistent_with_the_thin_lens_and_the_state(reference) -> None:
    config = _quiet(reference)
    source, state, clock = _scene(config, _static(6.0, x=0.5, y=-0.1))
    optics = source.optics
    state.focus.jump(0x2000, clock())
    state.pan.jump(3.0, clock())
    source.render_frame(7)
    truth = source.truth_for(7)
    assert truth is not None
    f = optics.focal_length_mm(config.zoom_counts)
    cam = np.array((0.5, -0.1, 6.0)) @ world_from_camera(3.0, 0.0)
    assert truth.position_camera_m == pytest.approx(tuple(cam))
    assert truth.z_m == pytest.approx(cam[2])
    assert truth.v_mm == pytest.approx(f * truth.z_m * 1000 / (truth.z_m * 1000 - f))
    assert truth.focus_counts == truth.focus_counts_commanded == 0x2000
    assert truth.v0_mm == pytest.approx(optics.lens_to_sensor_mm(0x2000, config.zoom_counts))
    d = optics.aperture_mm(config.zoom_counts)
    b = 0.5 * d * abs(truth.v0_mm - truth.v_mm) / truth.v_mm / optics.pixel_pitch_mm
    assert truth.blur_radius_px == pytest.approx(b)
    assert truth.r_px == pytest.approx(f / optics.pixel_pitch_mm * 0.03576 / truth.z_m, rel=0.01)
    assert truth.t == source.frame_time(7)
    assert not (truth.focus_moving)
    assert not (truth.pan_tilt_moving)
    assert not (truth.zoom_moving)
    assert truth.in_view


def test_transit_frames_and_focus_jitter_are_recorded(reference) -> None:
    config = with_overrides(_quiet(reference), {"lens.focus_jitter_counts": 5.0})
    source, state, clock = _scene(config, _static(4.0))
    clock.set(source.frame_time(0))
    move_s = 0.002  # starts 1 ms before mid-exposure, lands within the 4 ms exposure
    state.focus.move_to(0x3000, speed=(0x3000 - 0x1000) / move_s, t=clock() - 0.001)
    source.render_frame(0)
    first = source.truth_for(0)
    assert first is not None
    assert first.focus_moving
    clock.set(source.frame_time(1))
    source.render_frame(1)
    source.render_frame(2)
    settled, still = source.truth_for(1), source.truth_for(2)
    assert settled is not None
    assert still is not None
    assert not settled.focus_moving
    assert settled.focus_counts_commanded == pytest.approx(0x3000)
    assert abs(settled.focus_counts - 0x3000) > 0.01  # repeatability error of this move…
    assert still.focus_counts == settled.focus_counts  # … kept until the next move


def test_focus_oracle_gives_the_counts_that_make_the_target_sharp(reference) -> None:
    source, state, clock = _scene(_quiet(reference), _static(4.0))
    state.focus.jump(source.focus_oracle(clock()), clock())
    source.render_frame(0)
    truth = source.truth_for(0)
    assert truth is not None
    assert truth.blur_radius_px == pytest.approx(0.0, abs=1e-6)
    assert source.focus_oracle(clock()) == pytest.approx(truth.focus_counts)


def test_truth_table_is_bounded(reference) -> None:
    config = with_overrides(reference, {"capture.truth_frames": 16})
    source, _, _ = _scene(config, _static(5.0))
    for i in range(20):
        source.render_frame(i)
    assert source.truth_for(3) is None
    assert source.truth_for(19) is not None


def test_frames_are_deterministic_and_noise_has_the_modelled_spread(reference) -> None:
    a, _, _ = _scene(reference, _static(5.0))
    b, _, _ = _scene(reference, _static(5.0))
    first = a.render_frame(3).image
    assert np.array_equal(first, b.render_frame(3).image)
    assert not np.array_equal(first, a.render_frame(4).image)
    background = first[:100, :100].astype(np.float64)
    expected = math.sqrt(
        40.0 / reference.sensor.gain_e_per_dn + reference.sensor.read_noise_dn**2 + 1.0 / 12.0
    )  # + quantisation
    assert background.mean() == pytest.approx(40.0, abs=0.1)
    assert background.std() == pytest.approx(expected, rel=0.05)


def test_motion_blur_follows_the_image_motion_during_the_exposure(reference) -> None:
    config = _quiet(reference)
    world = WorldConfig(
        trajectory=TrajectoryConfig(
            kind="linear", position_m=(-1.0, 0.0, 5.0), end_m=(1.0, 0.0, 5.0), speed_mps=1.0
        )
    )
    source, _, _ = _scene(config, world)
    source.render_frame(30)
    truth = source.truth_for(30)
    assert truth is not None
    f_px = source.optics.focal_length_mm(config.zoom_counts) / source.optics.pixel_pitch_mm
    expected = f_px * 1.0 * config.capture.exposure_s / 5.0
    assert truth.motion_px[0] == pytest.approx(expected, rel=0.01)
    assert truth.motion_px[1] == pytest.approx(0.0, abs=1e-6)


def test_aruco_target_is_detected_by_opencv(reference) -> None:
    world = _static(1.5, shape="aruco", size_m=0.06, aruco_id=7)
    source, state, _ = _scene(reference, world)
    _focus_at(state, source.optics, 1.5)
    image = source.render_frame(0).image
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None
    assert ids.ravel().tolist() == [7]
    side_px = float(np.linalg.norm(corners[0][0][0] - corners[0][0][1]))
    marker_m = source.world.shape.aruco_marker_side_m
    assert marker_m is not None
    f_px = source.optics.focal_length_mm(reference.zoom_counts) / source.optics.pixel_pitch_mm
    assert side_px == pytest.approx(f_px * marker_m / 1.5, rel=0.02)


# -- trajectories -----------------------------------------------------------------------------


def test_circle_trajectory_is_a_horizontal_circle_at_the_given_speed() -> None:
    path = make_trajectory(
        TrajectoryConfig(kind="circle", center_m=(0, 0, 6), radius_m=4, speed_mps=0.25)
    )
    start = path.position(0.0)
    assert start == pytest.approx((0.0, 0.0, 2.0))  # phase 0: nearest the camera
    for t in (0.0, 13.0, 77.0):
        p = path.position(t)
        assert math.hypot(p[0], p[2] - 6.0) == pytest.approx(4.0)
        assert p[1] == 0.0
        step = np.linalg.norm(path.position(t + 0.01) - p) / 0.01
        assert step == pytest.approx(0.25, rel=1e-3)


def test_figure_eight_has_constant_speed_and_spans_the_half_extent() -> None:
    path = make_trajectory(
        TrajectoryConfig(kind="figure-eight", center_m=(0, 0, 5), radius_m=2, speed_mps=0.3)
    )
    pts = np.array([path.position(t) for t in np.arange(0.0, 60.0, 0.05)])
    speeds = np.linalg.norm(np.diff(pts, axis=0), axis=1) / 0.05
    assert np.median(speeds) == pytest.approx(0.3, rel=0.01)
    assert pts[:, 2].min() == pytest.approx(3.0, abs=0.02)
    assert pts[:, 2].max() == pytest.approx(7.0, abs=0.02)


def test_random_trajectory_is_seeded_smooth_and_inside_its_box() -> None:
    cfg = TrajectoryConfig(
        kind="random", center_m=(0, 0, 6), extent_m=(2, 0.3, 3), speed_mps=0.3, seed=4
    )
    a, b = make_trajectory(cfg), make_trajectory(cfg)
    other = make_trajectory(cfg.model_copy(update={"seed": 5}))
    times = np.arange(0.0, 300.0, 0.1)
    pts = np.array([a.position(t) for t in times])
    assert np.array_equal(pts[17], b.position(times[17]))
    assert not np.allclose(pts[17], other.position(times[17]))
    assert np.all(np.abs(pts - (0, 0, 6)) <= np.array((2, 0.3, 3)) + 1e-9)
    speed = np.linalg.norm(np.diff(pts, axis=0), axis=1) / 0.1
    assert speed.mean() == pytest.approx(0.3, rel=0.15)


def test_linear_trajectory_stops_at_its_end() -> None:
    path = make_trajectory(
        TrajectoryConfig(kind="linear", position_m=(0, 0, 10), end_m=(0, 0, 2), speed_mps=0.5)
    )
    assert path.position(4.0) == pytest.approx((0, 0, 8))
    assert path.position(100.0) == pytest.approx((0, 0, 2))


# -- ground-truth lens file -------------------------------------------------------------------


def test_lens_file_is_generated_from_the_simulator(reference) -> None:
    optics = Optics.from_config(reference)
    text = LENS_FILE.read_text(encoding="utf-8")
    assert text == optics.lens_table_toml(reference.zoom_counts), (
        "regenerate: python -m drivers.sim.optics --write dffd/defaults/lenses/sim-evi-d100.toml"
    )
    lens = tomllib.loads(text)["lens"]
    assert lens["focal_length_mm"] == optics.focal_length_mm(reference.zoom_counts)
    assert lens["pixel_pitch_mm"] == reference.sensor.pixel_pitch_mm
    assert lens["zoom_counts"] == reference.zoom_counts
    counts = np.array([c for c, _ in lens["focus_table"]], dtype=np.float64)
    v = np.array([v for _, v in lens["focus_table"]])
    assert counts[0] == 0x1000
    assert counts[-1] == 0x8400
    assert np.all(np.diff(counts) > 0)
    assert np.all(np.diff(v) > 0)
    for c, v_mm in zip(counts, v, strict=True):
        assert v_mm == pytest.approx(optics.lens_to_sensor_mm(c, reference.zoom_counts), abs=1e-6)
    # What the estimator does with it (monotone PCHIP) reproduces the simulator between rows.
    pchip = PchipInterpolator(counts, v)
    mid = np.linspace(counts[0], counts[-1], 997)
    truth = np.array([optics.lens_to_sensor_mm(c, reference.zoom_counts) for c in mid])
    assert np.max(np.abs(pchip(mid) - truth)) < 1e-5


def test_counts_map_is_nonlinear_and_inverts(reference) -> None:
    optics = Optics.from_config(reference)
    for z in (0.8, 1.0, 2.5, 10.0, 50.0):
        assert optics.focus_distance_m(optics.focus_counts_for_depth(z)) == pytest.approx(z)
    assert optics.focus_distance_m(0x1000) == math.inf
    far_slope = optics.focus_counts_for_depth(20.0) - optics.focus_counts_for_depth(math.inf)
    near_slope = optics.focus_counts_for_depth(0.8) - optics.focus_counts_for_depth(0.8 / 0.95)
    assert far_slope / (1 / 20.0) > 1.5 * near_slope / (1 / 0.8 - 0.95 / 0.8)


# -- live source ------------------------------------------------------------------------------


async def test_live_source_delivers_timestamped_frames_without_truth(reference) -> None:
    state = camera_state_for(reference)
    source = SimFrameSource.from_config(reference, state)
    assert isinstance(source, FrameSource)
    await source.start()
    try:
        frames = []
        for _ in range(3):
            async with asyncio.timeout(FRAME_TIMEOUT_S):
                frames.append(await source.next_frame())
    finally:
        await source.close()
    await source.close()  # idempotent
    assert [f.index for f in frames] == list(range(frames[0].index, frames[0].index + 3))
    assert np.diff([f.t for f in frames]) == pytest.approx([1 / 30, 1 / 30])
    assert all(isinstance(f, Frame) and f.image.shape == (480, 640) for f in frames)
    assert not hasattr(frames[0], "truth")
    truth = source.truth_for(frames[-1].index)
    assert truth is not None
    assert truth.t == frames[-1].t


async def test_live_source_counts_frames_lost_while_the_loop_stalled(reference) -> None:
    clock = VirtualClock(50.0)
    state = CameraState(clock=clock, initial_zoom=reference.zoom_counts)
    source = SimFrameSource(
        state,
        World.from_config(_static(5.0)),
        Optics.from_config(reference),
        CaptureConfig(queue_frames=2),
    )
    await source.start()
    clock.advance(1.0)  # a one-second stall before the first delivery
    try:
        async with asyncio.timeout(FRAME_TIMEOUT_S):
            frame = await source.next_frame()
    finally:
        await source.close()
    assert source.dropped_frames >= 25
    assert frame.index == source.dropped_frames


async def test_close_wakes_a_waiting_consumer(reference) -> None:
    config = with_overrides(reference, {"capture.capture_latency_frames": 10.0})
    source = SimFrameSource.from_config(config, camera_state_for(config))
    await source.start()
    waiter = asyncio.create_task(source.next_frame())
    await asyncio.sleep(0)  # let it start waiting (first delivery is ≥ 0.33 s away)
    await source.close()
    async with asyncio.timeout(FRAME_TIMEOUT_S):
        with pytest.raises(FrameSourceError):
            await waiter


def test_a_smear_longer_than_the_frame_is_cut_to_its_diagonal() -> None:
    # A search sweep slews the head during an exposure; one end of the exposure can project
    # tens of thousands of pixels away. The smear is cut to the frame's diagonal, so the patch
    # stays bounded (before: a 21,469 px smear asked for a 3.4 GiB kernel and the run was killed).
    angles = np.linspace(0.0, 2.0 * math.pi, 32, endpoint=False)
    outline = np.stack([320.0 + 20.0 * np.cos(angles), 240.0 + 20.0 * np.sin(angles)], axis=1)
    target = TargetImage(outline_px=outline, foreground_dn=200.0)
    kernel = np.ones((3, 3), dtype=np.float32) / 9.0
    frame_size = (640, 480)
    diagonal = math.hypot(*frame_size)
    patch = render_patch(target, 50.0, kernel, (21469.0, -300.0), frame_size)
    assert patch is not None
    height, width = patch.image.shape
    assert width <= 640 + diagonal + 20
    assert height <= 480 + diagonal + 20
    # Still the target's light, spread along the (cut) smear: brighter than the background.
    assert float(patch.image.max()) > 50.0
    assert float(patch.image.max()) < 200.0
    # A smear within the frame is rendered as before.
    short = render_patch(target, 50.0, kernel, (30.0, 0.0), frame_size)
    assert short is not None
    assert short.image.shape[1] < 200
