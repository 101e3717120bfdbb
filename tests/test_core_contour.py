"""Acquisition and active-contour tracking on synthetic images."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dffd.core.contour import ContourTracker, TrackerConfig, find_target, radius_of, resample_closed
from dffd.core.synthetic import render_disc

W, H = 640, 480


def test_radius_of_a_circle_is_its_radius_and_rotation_invariant() -> None:
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    pts = np.column_stack([100 + 30 * np.cos(a), 50 + 30 * np.sin(a)])
    assert radius_of(pts) == pytest.approx(30.0)
    ell = np.column_stack([40 * np.cos(a), 10 * np.sin(a)])
    rot = np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])
    e1 = resample_closed(ell, 64)
    e2 = resample_closed(ell @ rot.T, 64)
    assert radius_of(e1) == pytest.approx(radius_of(e2), rel=1e-3)


def test_acquires_the_disc_among_clutter_from_an_roi() -> None:
    rng = np.random.default_rng(0)
    img = render_disc(W, H, (320.4, 240.2), 40.0, 0.0, rng=rng)
    cv2.rectangle(img, (20, 20), (90, 60), 255, -1)  # clutter far from the ROI
    poly = find_target(img, (250, 170, 140, 140))
    assert poly is not None
    assert np.allclose(poly.mean(axis=0), (320.4, 240.2), atol=1.0)
    assert find_target(np.full((H, W), 30, np.uint8)) is None


@pytest.mark.parametrize("bgr", [False, True])
def test_tracks_a_moving_growing_disc_with_subpixel_size(bgr: bool) -> None:
    rng = np.random.default_rng(1)
    tracker = ContourTracker(TrackerConfig())
    c0, r0 = np.array([300.3, 230.7]), 45.0
    img = render_disc(W, H, tuple(c0), r0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    errs = []
    for k in range(1, 40):
        c = c0 + k * np.array([1.2, -0.6])
        r = r0 * (1 + 0.004 * k)
        blur = 4.0 if k % 4 == 0 else 0.0  # burst-like defocused frames in between
        img = render_disc(W, H, tuple(c), r, blur, rng=rng)
        frame = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if bgr else img
        obs = tracker.update(frame, k / 30, "similarity")
        assert obs.ok
        if blur == 0:
            errs.append((obs.r_px - r, *(np.asarray(obs.centroid) - c)))
    e = np.asarray(errs)
    assert np.abs(e[:, 1:]).max() < 0.1  # centroid
    assert np.std(e[:, 0]) < 0.03  # r noise (px)
    assert abs(np.mean(e[:, 0])) < 0.15  # r bias (px)
    assert np.isfinite(obs.peak_sq).sum() > 50


def test_declares_the_target_lost_when_it_disappears() -> None:
    rng = np.random.default_rng(2)
    cfg = TrackerConfig(lost_after_frames=3)
    tracker = ContourTracker(cfg)
    img = render_disc(W, H, (320, 240), 30.0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    empty = render_disc(W, H, (-500, -500), 30.0, 0.0, rng=rng)
    for k in range(3):
        assert not tracker.lost
        obs = tracker.update(empty, 1 + k / 30, "similarity")
        assert not obs.ok
    assert tracker.lost


def test_transit_frames_update_translation_only() -> None:
    rng = np.random.default_rng(3)
    tracker = ContourTracker(TrackerConfig())
    img = render_disc(W, H, (320, 240), 40.0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    r_before = radius_of(tracker.points) if tracker.points is not None else 0.0
    moved = render_disc(W, H, (323, 241), 42.0, 3.0, rng=rng)
    obs = tracker.update(moved, 1 / 30, "translation")
    assert obs.centroid == pytest.approx((323, 241), abs=0.2)
    # contour size untouched (resampling only); r_px adds the curvature correction
    assert radius_of(obs.points) == pytest.approx(r_before, abs=1e-3)


@pytest.mark.parametrize("radius", [22.0, 40.0, 85.0])
def test_size_is_unbiased_on_small_blurred_discs(radius: float) -> None:
    # the |∇I| maximum of a blurred disc lies σ²/2a inside it (−0.04 px at 22 px uncorrected)
    errs = []
    for k in range(4):
        rng = np.random.default_rng(10 + k)
        centre = (320.3 + 0.17 * k, 240.1 + 0.29 * k)
        img = render_disc(W, H, centre, radius, 0.0, rng=rng)
        tracker = ContourTracker(TrackerConfig())
        poly = find_target(img)
        assert poly is not None
        assert tracker.start(img, poly, 0.0)
        obs = tracker.update(img, 0.0, "similarity")
        assert math.isfinite(obs.edge_sigma_px)
        errs.append(obs.r_px - radius)
    assert abs(float(np.mean(errs))) < 0.012


def test_one_frame_jump_does_not_shrink_the_contour() -> None:
    # a 12 px pan/tilt jump: one linearised pass would shrink r by |t|²/4a ≈ 1.5 px at 24 px
    rng = np.random.default_rng(5)
    tracker = ContourTracker(TrackerConfig())
    img = render_disc(W, H, (300.0, 240.0), 24.0, 0.0, rng=rng)
    poly = find_target(img)
    assert poly is not None
    assert tracker.start(img, poly, 0.0)
    jumped = render_disc(W, H, (312.0, 236.0), 24.0, 0.0, rng=rng)
    obs = tracker.update(jumped, 1 / 30, "similarity")
    assert obs.ok
    assert obs.r_px == pytest.approx(24.0, abs=0.03)
    assert obs.centroid == pytest.approx((312.0, 236.0), abs=0.1)
