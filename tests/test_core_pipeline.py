"""The pipeline end to end on closed-loop synthetic streams (the issue's accuracy targets)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from dffd.config import DffdConfig
from dffd.core.acquisition import find_target
from dffd.core.pipeline import Measurement, Pipeline
from dffd.core.sizes import SizeHistory, SizeOffset
from dffd.core.synthetic import DiscScene, closed_loop, render_disc, render_scene, synthetic_lens
from dffd.core.types import FrameTag
from dffd.literals import FocusMeasure
from dffd.wiring import pipeline_config
from drivers.frames import Frame

# The service's estimation settings (their one set of defaults lives in the config).
SERVICE = pipeline_config(DffdConfig())

LENS = synthetic_lens()
SCENE = DiscScene()
R = 0.03576


def circle(t: float) -> tuple[float, float, float]:
    """Paper-like: a circle of 3 m radius whose centre is 6 m away (z 3..9 m), period 20 s."""
    w = 2 * math.pi / 20
    return 0.0, 0.0, math.hypot(6 + 3 * math.cos(w * t), 3 * math.sin(w * t))


@pytest.fixture(scope="module")
def paper_run() -> dict[str, np.ndarray]:
    # this synthetic circle turns in 20 s (~1 m/s) and settles in 5 s: the observer poles it
    # was tuned with (the default 0.15 rad/s is for the slower reference-simulator circle); its
    # closed loop has no focus travel, a burst follows the plan at once: no plan lead and no
    # measurement time offset (the reference simulator's bracket lean, docs/estimation.md §7)
    pipe = Pipeline(
        replace(
            SERVICE, known_size_m=R, lpv_omega=0.6, plan_lead_s=0.0, measurement_time_offset_s=0.0
        ),
        LENS,
    )
    est: dict[str, list[tuple[float, float]]] = {k: [] for k in ("cf1", "cf2", "lpv", "kf")}
    meas: list[tuple[float, float]] = []
    sizes: list[float] = []
    n_rej = 0
    for st in closed_loop(pipe, SCENE, LENS, circle, duration_s=25.0, seed=7):
        out = pipe.process(st.frame, st.tag)
        m = out.measurement
        if m is not None:
            if m.accepted and m.z_m is not None:
                meas.append((m.t, m.z_m - circle(m.t)[2]))
            else:
                n_rej += 1
        e = out.estimate
        if e is not None and e.z_m is not None:
            for k, rows in est.items():
                value = e.depth_m[k]
                if value is not None:
                    rows.append((e.t, value - st.truth_m[2]))
            if e.size_m is not None:
                sizes.append(e.size_m)
            assert e.state == "tracking"
            assert e.sigma_m is not None
            assert e.position_m is not None
    out_arr = {k: np.asarray(v) for k, v in est.items()}
    out_arr["measured"] = np.asarray(meas)
    out_arr["size"] = np.asarray(sizes)
    out_arr["rejected"] = np.asarray([n_rej])
    return out_arr


def _ss_std(a: np.ndarray, settle: float = 5.0) -> float:
    return float(np.std(a[a[:, 0] >= settle, 1]))


def test_paper_like_accuracy_on_synthetic_images(paper_run: dict[str, np.ndarray]) -> None:
    raw = _ss_std(paper_run["measured"])
    lpv = _ss_std(paper_run["lpv"])
    cf2 = _ss_std(paper_run["cf2"])
    assert len(paper_run["measured"]) > 80
    assert paper_run["rejected"][0] <= 3
    assert lpv < 0.0377  # the paper's best
    # Estimates on every frame (not only tracking frames); the LPV/raw ratio of this 25-s run
    # is mostly sampling noise of its 86 bursts: 0.545 / 0.452 / 0.532 for closed-loop seeds
    # 7 / 8 / 9 with the same code (it was 0.495 at seed 7 with estimates on tracking frames).
    assert lpv <= 0.55 * raw
    # LPV about as good as CF2: 1.14x at this seed since CF2's nominal size no longer takes the
    # first bracket's 35 %-off blurred sizes (CF2 5.8 -> 5.1 mm, LPV unchanged); 0.97x / 1.02x
    # at closed-loop seeds 8 / 9 (docs/estimation.md §11).
    assert lpv <= cf2 * 1.15
    for name in ("cf1", "kf"):
        assert _ss_std(paper_run[name]) <= 0.5 * raw, (name, _ss_std(paper_run[name]), raw)
    # R̂ converges to the real size
    assert np.median(paper_run["size"][-100:]) == pytest.approx(R, rel=0.01)


def _frame(index: int, t: float, z: float, counts: int, x: float = 0.0) -> tuple[Frame, FrameTag]:
    img = render_scene(SCENE, LENS, counts, (x, 0.0, z), np.random.default_rng(index))
    return Frame(index, t, img), FrameTag("track", counts, 0.0, 0.0)


def test_state_machine_acquire_release_lost_and_reacquire() -> None:
    pipe = Pipeline(SERVICE, LENS)
    c = LENS.counts_for_depth(4.0)
    out = pipe.process(*_frame(0, 0.0, 4.0, c))
    assert out.state == "tracking"
    assert out.estimate is not None
    assert out.estimate.z_m is None  # no depth before the first burst
    pipe.release()
    assert pipe.state == "idle"
    assert pipe.process(*_frame(1, 0.033, 4.0, c)).state == "idle"  # held after release
    # the disc is about 34 px wide at 4 m: an ROI around it acquires it
    pipe.acquire_roi(260, 180, 120, 120)
    assert pipe.process(*_frame(2, 0.066, 4.0, c)).state == "tracking"
    # the target leaves the image: lost after a few frames, then found again
    states = [pipe.process(*_frame(3 + k, 0.1 + k / 30, 4.0, c, x=50.0)).state for k in range(4)]
    assert states[-1] == "lost"
    found = [pipe.process(*_frame(10 + k, 0.3 + k / 30, 4.0, c)).state for k in range(6)]
    assert found[-1] == "tracking"
    with pytest.raises(ValueError, match="positive size"):
        pipe.acquire_roi(0, 0, 0, 10)
    # released, then back to automatic detection without an ROI
    pipe.release()
    assert pipe.process(*_frame(20, 0.6, 4.0, c)).state == "idle"
    pipe.acquire_auto()
    assert pipe.state == "acquiring"
    assert pipe.process(*_frame(21, 0.633, 4.0, c)).state == "tracking"


def test_incomplete_burst_is_rejected_and_plan_uses_the_prediction() -> None:
    pipe = Pipeline(SERVICE, LENS)
    c = LENS.counts_for_depth(5.0)
    assert pipe.predicted_depth() is None
    pipe.process(*_frame(0, 0.0, 5.0, c))
    frame, _ = _frame(1, 0.033, 5.0, c + 2000)
    pipe.process(frame, FrameTag("burst", c + 2000, 0.0, 0.0, (0, 0)))
    out = pipe.process(*_frame(2, 0.066, 5.0, c))  # a track frame ends the burst early
    # Not emitted (the …/measurement schema needs three frames): counted with its reason.
    assert out.measurement is None
    assert pipe.burst_rejections == {"1 of 3 frames with a focus cost": 1}
    plan = pipe.plan_burst(c)
    assert len(set(plan)) == 3


def test_deterministic() -> None:
    def run() -> list[float | None]:
        pipe = Pipeline(SERVICE, LENS)
        zs = []
        for st in closed_loop(pipe, SCENE, LENS, circle, duration_s=3.0, seed=1):
            e = pipe.process(st.frame, st.tag).estimate
            zs.append(None if e is None else e.z_m)
        return zs

    assert run() == run()


@pytest.mark.parametrize("measure", ["peak_gradient", "edge_variance", "debiased_peak"])
def test_rolling_bursts_close_with_the_previous_end_and_the_middle_frame(
    measure: FocusMeasure,
) -> None:
    """Triangle lo, mid, hi, mid, lo, …: every end (tagged slot 2 alone) closes a burst with the
    previous end and the tracking frame between; the fit is accurate and motion-compensated
    with either focus measure."""
    pipe = Pipeline(replace(SERVICE, plan_lead_s=0.0, focus_measure=measure), LENS)
    rng = np.random.default_rng(3)
    dt, index, bid = 1.0 / 30, 0, 0
    z0, zdot = 5.0, -0.25  # approaching at 0.25 m/s

    def shot(counts: int, tag: FrameTag) -> Measurement | None:
        nonlocal index
        t = index * dt
        img = render_scene(SCENE, LENS, counts, (0.0, 0.0, z0 + zdot * t), rng)
        index += 1
        return pipe.process(Frame(index - 1, t, img), tag).measurement

    mid = LENS.counts_for_depth(z0)
    for _ in range(3):
        shot(mid, FrameTag("track", mid, 0.0, 0.0))
    side, measurements, opened = -1, [], 0
    for _ in range(24):
        plan = pipe.plan_burst(mid)
        lo, mid, hi = sorted(plan)
        end = hi if side > 0 else lo
        side = -side
        for _ in range(3):
            index += 1  # transit frames of the move (not shown to the core)
        bid += 1
        m = shot(end, FrameTag("burst", end, 0.0, 0.0, (bid, 2)))
        assert m is None  # fitted at the next tracking frame
        index += 3
        m = shot(mid, FrameTag("track", mid, 0.0, 0.0))
        if m is None:
            opened += 1
            continue
        assert len(m.frame_indices) == 3
        assert m.frame_indices[-1] == index - 5  # this end, with the earlier end and a middle
        assert len(set(m.focus_counts)) == 3
        measurements.append(m)
    assert opened == 1  # only the first end opens a sequence
    # edge moments: only the full-range bracket's far end (no depth yet) overflows the normal
    # lines, in the two bursts it closes
    assert pipe.measure_fallbacks == (0 if measure == "peak_gradient" else 2)
    accepted = [m for m in measurements if m.accepted and m.z_m is not None]
    assert len(accepted) >= 20
    errors = [m.z_m - (z0 + zdot * m.t) for m in accepted[3:] if m.z_m is not None]
    assert abs(float(np.mean(errors))) < 0.02
    assert float(np.std(errors)) < 0.03


def test_rolling_end_after_a_same_side_end_opens_a_new_sequence() -> None:
    pipe = Pipeline(SERVICE, LENS)
    c = LENS.counts_for_depth(5.0)
    pipe.process(*_frame(0, 0.0, 5.0, c))
    frame, _ = _frame(1, 0.2, 5.0, c + 2000)
    pipe.process(frame, FrameTag("burst", c + 2000, 0.0, 0.0, (1, 2)))
    pipe.process(*_frame(2, 0.4, 5.0, c))
    frame, _ = _frame(3, 0.6, 5.0, c + 1900)  # the same side: no bracket around the middle
    pipe.process(frame, FrameTag("burst", c + 1900, 0.0, 0.0, (2, 2)))
    out = pipe.process(*_frame(4, 0.8, 5.0, c))
    assert out.measurement is None
    assert not pipe.burst_rejections


def test_rolling_end_of_another_bracket_opens_a_new_sequence() -> None:
    # Ends on both sides of the middle but 10x apart: the first end belongs to an older, wider
    # plan (the full-range first burst); a bracket of the two would be fitted from a lopsided
    # triple (on the demo 1.7 m off). The second end opens a sequence; the next one closes it.
    pipe = Pipeline(SERVICE, LENS)
    c = LENS.counts_for_depth(5.0)
    pipe.process(*_frame(0, 0.0, 5.0, c))
    frame, _ = _frame(1, 0.2, 5.0, c + 2000)
    pipe.process(frame, FrameTag("burst", c + 2000, 0.0, 0.0, (1, 2)))
    pipe.process(*_frame(2, 0.4, 5.0, c))
    frame, _ = _frame(3, 0.6, 5.0, c - 200)
    pipe.process(frame, FrameTag("burst", c - 200, 0.0, 0.0, (2, 2)))
    assert pipe.process(*_frame(4, 0.8, 5.0, c)).measurement is None
    frame, _ = _frame(5, 1.0, 5.0, c + 210)
    pipe.process(frame, FrameTag("burst", c + 210, 0.0, 0.0, (3, 2)))
    out = pipe.process(*_frame(6, 1.2, 5.0, c))
    assert out.measurement is not None
    assert sorted(out.measurement.focus_counts) == [c - 200, c, c + 210]


def test_every_frame_with_a_contour_yields_an_estimate() -> None:
    """Burst and transit frames step the estimators too: estimates at the frame rate."""
    pipe = Pipeline(replace(SERVICE, plan_lead_s=0.0, measurement_time_offset_s=0.0), LENS)
    roles: dict[str, int] = {}
    with_depth: dict[str, int] = {}
    frames = 0
    for st in closed_loop(pipe, SCENE, LENS, circle, duration_s=4.0, transit=True, seed=2):
        e = pipe.process(st.frame, st.tag).estimate
        frames += 1
        if e is None:
            continue
        roles[st.tag.role] = roles.get(st.tag.role, 0) + 1
        if e.z_m is not None:
            with_depth[st.tag.role] = with_depth.get(st.tag.role, 0) + 1
            assert e.position_world_m is not None
            if e.t > 2.0:  # after the first, coarse full-range bursts
                assert abs(e.z_m - st.truth_m[2]) < 0.1, (st.tag.role, e.t)
    assert sum(roles.values()) >= 0.9 * frames
    assert set(with_depth) == {"track", "burst", "transit"}


def test_size_history_interpolates_and_fits_a_line() -> None:
    h = SizeHistory(4)
    assert h.ln_at(0.0) is None
    assert h.line(0.0, 1.0) is None
    for k in range(6):  # ln s = 0.1 t, the oldest two frames fall out
        h.add(0.1 * k, math.exp(0.01 * k))
    assert len(h) == 4
    assert h.ln_at(0.25) == pytest.approx(0.025)
    assert h.ln_at(0.0) == pytest.approx(0.02)  # held before the oldest kept frame
    assert h.ln_at(9.0) == pytest.approx(0.05)  # and after the newest
    line = h.line(0.3, math.inf)
    assert line is not None
    t_ref, ln_ref, slope = line
    assert (t_ref, ln_ref, slope) == pytest.approx((0.4, 0.04, 0.1))
    h.add(0.5, math.exp(0.07))  # not after the newest: replaces it
    assert h.ln_at(0.5) == pytest.approx(0.07)
    with pytest.raises(ValueError, match="at least 2"):
        SizeHistory(1)


@pytest.mark.parametrize("moving", [True, False])
def test_size_offset_is_recovered_where_the_motion_observes_it(moving: bool) -> None:
    """s_m = R/z + δ p/f with δ = +0.17 px (the offset seen on independent recordings): bursts
    on a circle 3-9 m (z_m noise ∝ z²) recover it; at rest it is unobservable and stays at 0."""
    p_over_f = LENS.pixel_pitch_mm / LENS.focal_length_mm
    delta_px = 0.17
    offset = SizeOffset(0.5 * p_over_f)
    rng = np.random.default_rng(5)
    for k in range(300):  # ~2 minutes of bursts at 2.2 Hz
        z = circle(k / 2.2)[2] if moving else 6.0
        sigma_z = 6e-4 * z * z  # ~20 mm at 6 m
        offset.add(z + sigma_z * rng.standard_normal(), sigma_z, R / z + delta_px * p_over_f)
    est = offset.estimate()
    assert est is not None
    d, sigma_d = est
    if moving:
        assert d / p_over_f == pytest.approx(delta_px, abs=0.03)
        assert sigma_d / p_over_f < 0.03
    else:
        assert abs(d / p_over_f) < 0.01


def test_no_burst_is_fitted_across_a_depth_jump() -> None:
    """A burst after which the target is seen 10 % nearer on a tracking frame (a jump in depth)
    is dropped with its reason: no size is interpolated across the jump. The same burst without
    the jump is fitted."""

    def run(z_after: float) -> Pipeline:
        pipe = Pipeline(SERVICE, LENS)
        c = LENS.counts_for_depth(5.0)
        k = 0

        def shot(z: float, counts: int, tag: FrameTag | None = None) -> Measurement | None:
            nonlocal k
            frame, track = _frame(k, k / 30, z, counts)
            k += 1
            return pipe.process(frame, tag or track).measurement

        for _ in range(3):
            shot(5.0, c)
        for bid in (1, 2):  # the first burst gives a depth; the jump comes after the second
            for slot, dc in enumerate((-1500, 1500, 0)):
                shot(5.0, c + dc, FrameTag("burst", c + dc, 0.0, 0.0, (bid, slot)))
            m = shot(5.0 if bid == 1 else z_after, c)
            assert (m is not None) == (bid == 1 or z_after == 5.0)
        return pipe

    assert run(4.5).burst_rejections == {"depth jump during the burst": 1}
    assert not run(5.0).burst_rejections


@pytest.mark.parametrize("end_offset", [3000, 4500])
def test_a_tracking_frame_held_at_a_bracket_end_is_no_depth_jump(end_offset: int) -> None:
    """The scheduler may hold the lens at a bracket's end for the frame that closes the burst
    (start-up). That frame is tagged ``track`` but defocused (> 1.5 px here), and on the
    reference simulator its size is off like a burst frame's (the synthetic disc's is not, so
    the size change is made here by rendering the target 10 % nearer): it is not tested for a
    jump, the burst is fitted and applied; the same frame at the best focus still is a jump."""

    def run(z_close: float, close_offset: int) -> tuple[Pipeline, list[Measurement]]:
        pipe = Pipeline(SERVICE, LENS)
        c = LENS.counts_for_depth(5.0)
        k = 0
        out: list[Measurement] = []

        def shot(z: float, counts: int, tag: FrameTag | None = None) -> None:
            nonlocal k
            frame, track = _frame(k, k / 30, z, counts)
            k += 1
            m = pipe.process(frame, tag or track).measurement
            if m is not None:
                out.append(m)

        for _ in range(3):
            shot(5.0, c)
        for bid in (1, 2):  # the first burst gives a depth; the second closes at its far end
            for slot, dc in enumerate((end_offset, 0, -end_offset)):
                shot(5.0, c + dc, FrameTag("burst", c + dc, 0.0, 0.0, (bid, slot)))
            if bid == 1:
                shot(5.0, c)
        for _ in range(2):  # the closing frame and one more, held where the burst ended
            shot(z_close, c + close_offset)
        return pipe, out

    pipe, out = run(4.5, -end_offset)
    assert not pipe.burst_rejections
    assert [m.accepted for m in out] == [True, True]
    assert out[1].z_m == pytest.approx(5.0, rel=0.05)  # the burst before the held frames
    pipe, out = run(4.5, 0)
    assert pipe.burst_rejections == {"depth jump during the burst": 1}


def test_size_measurement_is_the_applied_bursts_size_on_its_frame_only() -> None:
    """``Pipeline.size_measurement`` (the 3D tracker's size input): ``(R, σ_R)`` on the frame
    that applied an accepted burst, None on every other frame."""
    pipe = Pipeline(replace(SERVICE, plan_lead_s=0.0), LENS)
    sizes: list[tuple[float, float]] = []
    for st in closed_loop(pipe, SCENE, LENS, circle, duration_s=6.0, seed=4):
        e = pipe.process(st.frame, st.tag).estimate
        if e is None:
            continue
        size = pipe.size_measurement
        assert (size is not None) == (e.measured_t is not None), e.t
        if size is not None and e.t > 2.0:  # after the coarse full-range start-up bursts
            sizes.append(size)
    assert len(sizes) >= 5
    for size_m, sigma in sizes:
        assert 0 < sigma < 0.01 * R
        assert size_m == pytest.approx(R, abs=max(5 * sigma, 0.003 * R))


@pytest.mark.parametrize("compensate", [True, False])
def test_the_head_turning_under_a_still_target_is_in_the_contours_prediction(
    compensate: bool,
) -> None:
    """A still target 4 m ahead while the head pans right at 0.3° a frame (29 px of image
    motion, more than twice the normals' reach) from the 4th frame: the tags' pan in the
    prediction keeps an estimate on every frame; without it the target is lost."""
    pipe = Pipeline(replace(SERVICE, compensate_head_motion=compensate), LENS)
    c = LENS.counts_for_depth(4.0)
    pans = [0.0] * 3 + [0.3 * k for k in range(1, 7)] + [1.8] * 3
    estimates = []
    for i, pan in enumerate(pans):
        p = math.radians(pan)
        # the world point (0, 0, 4) in the camera frame of that pan (x right, turned right)
        pos = (-4.0 * math.sin(p), 0.0, 4.0 * math.cos(p))
        img = render_scene(SCENE, LENS, c, pos, np.random.default_rng(i))
        out = pipe.process(Frame(i, i / 30, img), FrameTag("track", c, pan, 0.0))
        estimates.append(out.estimate is not None)
    if compensate:
        assert all(estimates)
    else:
        assert not all(estimates)


@pytest.mark.parametrize("compensate", [True, False])
def test_the_search_after_a_loss_follows_the_heads_turn(compensate: bool) -> None:
    """A still target 4 m ahead is hidden (lost with the head still), the head pans 1.2° while
    it is gone (~116 px of image motion), and it shows again: the ROI around the last contour
    is moved by the head's turn and finds it on that very frame (before the whole frame is
    searched again); left at its old pixel it misses it."""
    pipe = Pipeline(replace(SERVICE, compensate_head_motion=compensate), LENS)
    c = LENS.counts_for_depth(4.0)

    def step(i: int, pan: float, visible: bool) -> str:
        p = math.radians(pan)
        # the world point (0, 0, 4) in the camera frame of that pan (far off when hidden)
        pos = (-4.0 * math.sin(p) + (0.0 if visible else 50.0), 0.0, 4.0 * math.cos(p))
        img = render_scene(SCENE, LENS, c, pos, np.random.default_rng(i))
        return pipe.process(Frame(i, i / 30, img), FrameTag("track", c, pan, 0.0)).state

    assert [step(i, 0.0, True) for i in range(3)] == ["tracking"] * 3
    # lost on the third hidden frame (the head still), then the ROI-only frames: the whole
    # frame is searched on every 5th frame after a loss
    assert [step(3 + k, 0.0, False) for k in range(3)] == ["tracking", "tracking", "lost"]
    assert [step(6 + k, 0.4 * (k + 1), False) for k in range(3)] == ["lost"] * 3
    found = step(9, 1.2, True)
    assert found == ("tracking" if compensate else "lost")


@pytest.mark.parametrize(
    ("roi", "found"),
    [((-300, 170, 140, 140), False), ((-40, 170, 140, 140), True), ((700, 170, 50, 50), False)],
)
def test_an_roi_outside_the_frame_is_cut_to_the_frame(
    roi: tuple[int, int, int, int], found: bool
) -> None:
    """An ROI partly outside the frame searches the part inside; one wholly outside finds
    nothing (it once searched a strip at the frame's edge instead)."""
    img = render_disc(640, 480, (60.0, 240.0), 20.0, 0.0, rng=np.random.default_rng(0))
    assert (find_target(img, roi) is not None) == found
