"""The search sweep is armed by one shared start-up step, in the daemon and the lock-step bench.

Before, only the daemon armed it (dffd/daemon/app.py): the bench's automatic acquisition never
swept, so its figures did not show what the service does when the target is out of view.
"""

from __future__ import annotations

from dffd.config import DffdConfig
from dffd.scheduler import Scheduler
from dffd.step import StepResult
from dffd.wiring import arm_search
from tests.test_scheduler_search import SEARCH


def test_automatic_acquisition_arms_the_sweep_and_an_roi_does_not() -> None:
    auto = Scheduler(SEARCH)
    arm_search(auto, DffdConfig(), 0.0)
    assert auto.search_armed
    status = auto.search_status
    assert status is not None
    assert status.phase == "waiting"
    pointed = Scheduler(SEARCH)
    arm_search(pointed, DffdConfig(target={"roi": [100, 100, 50, 50]}), 0.0)
    assert not pointed.search_armed
    assert pointed.search_status is None


def test_the_bench_sweeps_for_a_target_out_of_view() -> None:
    """``stop-and-go`` starts with the disc 16.7° left of the head (out of view, a 3.3° half
    field) and still there for 3 s: the bench sweeps after ``search_after_s`` = 3 s as the daemon
    does, and finds it within a few views (without the sweep: first acquired at 5.5 s, when the
    disc drifted into the view by itself)."""
    from hil.lockstep import run_session
    from hil.scenario import load_scenario

    scenario = load_scenario("stop-and-go").with_optics("reference")
    case, trajectory = scenario.expand()[0]
    steps: list[StepResult] = []
    run_session(scenario, case, trajectory, 1, duration_s=4.6, on_step=steps.append)
    first = next((s for s in steps if s.output.state == "tracking"), None)
    assert first is not None, "never acquired: the sweep did not run"
    before = [s for s in steps if s.frame_index < first.frame_index]
    # The head left its start to look (the first views are one field of view, 5.3°, apart).
    assert max(abs(s.tag.pan_deg) for s in before) > 4.0
    assert first.tag.pan_deg < -3.0  # found on the left, where the disc is
