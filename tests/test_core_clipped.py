"""A target cut by the frame's edge while acquiring: the head is told where to turn."""

from __future__ import annotations

import numpy as np
import pytest

from dffd.config import DffdConfig
from dffd.core.acquisition import find_target
from dffd.core.clipped import find_clipped_target
from dffd.core.contour import TrackerConfig
from dffd.core.pipeline import Pipeline
from dffd.core.synthetic import render_disc, synthetic_lens
from dffd.core.types import FrameTag
from dffd.step import CoreStep
from dffd.wiring import pipeline_config
from drivers.frames import Frame

SERVICE = pipeline_config(DffdConfig())
LENS = synthetic_lens()
W, H = 640, 480


def _image(center: tuple[float, float], radius_px: float = 50.0, seed: int = 0) -> np.ndarray:
    return render_disc(W, H, center, radius_px, 0.5, rng=np.random.default_rng(seed))


def _frame(index: int, image: np.ndarray) -> tuple[Frame, FrameTag]:
    t = index / 30.0
    return Frame(index, t, image), FrameTag("track", LENS.counts_for_depth(4.0), 0.0, 0.0)


@pytest.mark.parametrize(
    ("center", "side"),
    [((330.0, 462.0), "bottom"), ((15.0, 200.0), "left"), ((600.0, 30.0), "top right")],
)
def test_a_target_cut_by_the_edge_is_found_on_its_side(
    center: tuple[float, float], side: str
) -> None:
    """find_target takes only whole blobs; the cut-off disc's visible centroid is on its side
    of the frame, inside the part that shows."""
    gray = _image(center)
    assert find_target(gray) is None, side
    found = find_clipped_target(gray, TrackerConfig().min_radius_px)
    assert found is not None, side
    x, y = found
    assert 0 <= x < W
    assert 0 <= y < H
    assert np.hypot(x - center[0], y - center[1]) < 50.0  # within the disc
    # the visible part's centroid is nearer the frame's centre than the disc's own centre
    mid = (W / 2, H / 2)
    assert np.hypot(x - mid[0], y - mid[1]) < np.hypot(center[0] - mid[0], center[1] - mid[1])


def test_nothing_is_claimed_on_an_empty_frame_or_a_whole_target() -> None:
    empty = render_disc(W, H, (-500.0, -500.0), 10.0, 0.5, rng=np.random.default_rng(1))
    assert find_clipped_target(empty) is None
    # a whole disc is find_target's: no cut-off blob is reported beside it
    assert find_clipped_target(_image((320.0, 240.0))) is None


def test_while_acquiring_the_core_feeds_the_cut_off_centroid_to_the_head() -> None:
    """The core reports the cut-off target while it acquires, and the scheduler's feedback
    carries it as the centroid to turn to (without it: None, pan/tilt never moves, and a target
    starting half out of view is lost — ``random`` seed 2 on the bench acquired after 15 s);
    once the disc is whole it is acquired as usual and the candidate is gone."""
    core = CoreStep.build(SERVICE, LENS)
    step = core.step(*_frame(0, _image((330.0, 462.0))))
    assert step.output.state == "acquiring"
    assert step.output.candidate_px is not None
    assert step.feedback.centroid_px == step.output.candidate_px
    assert step.feedback.centroid_px[1] > H / 2  # below the centre: the head tilts down
    whole = core.step(*_frame(1, _image((330.0, 380.0))))
    assert whole.output.state == "tracking"
    assert whole.output.candidate_px is None
    assert whole.feedback.centroid_px is not None
    assert abs(whole.feedback.centroid_px[1] - 380.0) < 1.0


def test_release_forgets_the_candidate() -> None:
    pipe = Pipeline(SERVICE, LENS)
    assert pipe.process(*_frame(0, _image((330.0, 462.0)))).candidate_px is not None
    pipe.release()
    assert pipe.process(*_frame(1, _image((330.0, 462.0)))).candidate_px is None


def test_the_bench_target_that_starts_half_out_of_view_is_acquired_at_once() -> None:
    """``random`` seed 2 on the simulator: the disc starts cut by the bottom edge and leaves the
    view within a second. Turning to its cut-off part, the core tracks it from the first
    quarter-second (before: no estimate for 15 s, best ss RMS 223 mm over the run)."""
    from hil.lockstep import run_session
    from hil.scenario import load_scenario

    scenario = load_scenario("random").with_optics("reference")
    case, trajectory = scenario.expand()[0]
    result = run_session(scenario, case, trajectory, 2, duration_s=2.0)
    assert result.frames == 60
    assert result.estimate_frames >= 0.8 * result.frames


def test_after_a_sighting_the_search_owns_the_hunt() -> None:
    """Once a target was tracked, a loss is the scheduler's search sweep's to solve: no
    candidate then (the sweep reports its views; a cut-off blob would pre-empt it)."""
    pipe = Pipeline(SERVICE, LENS)
    assert pipe.process(*_frame(0, _image((320.0, 240.0)))).state == "tracking"
    pipe.acquire_auto()
    assert pipe.process(*_frame(1, _image((330.0, 462.0)))).candidate_px is None
