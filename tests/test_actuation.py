"""The action executor: scheduler actions → VISCA requests (pure), outcomes → scheduler callbacks,
and the daemon's actuator workers over a real link to the simulated camera."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from dffd.actuation import (
    completion_timeout_s,
    is_focus_action,
    report_done,
    report_failed,
    request_for,
)
from dffd.daemon.actuators import Actuators
from dffd.scheduler import (
    FocusInquiry,
    FocusMove,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltInquiry,
    PanTiltStop,
)
from drivers.sim.device_types import DeviceConfig
from drivers.visca import codec_replies, codec_requests
from drivers.visca.camera import EVI_D70, EVI_D100
from tests.visca_support import WAIT_S, sim_camera


class _Recorder:
    """Stands in for the scheduler: records the callbacks it receives, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.event = asyncio.Event() if _loop_running() else None

    def __getattr__(self, name: str) -> Any:
        if not name.startswith("on_"):
            raise AttributeError(name)

        def record(*args: Any) -> None:
            self.calls.append((name, *args))
            if self.event is not None:
                self.event.set()

        return record


def _loop_running() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def test_focus_actions_become_focus_requests() -> None:
    assert request_for(FocusMove(7, 0x2345), EVI_D100) == codec_requests.FocusDirect(0x2345)
    assert request_for(FocusInquiry(), EVI_D100) == codec_requests.FocusPositionInquiry()
    assert is_focus_action(FocusMove(1, 0x2000))
    assert is_focus_action(FocusInquiry())
    assert not is_focus_action(PanTiltStop())
    with pytest.raises(ValueError, match="outside"):
        request_for(FocusMove(1, 0x0FFF), EVI_D100)  # nearer than the far end of the D100
    # The D70 focuses nearer (to 0xC000): the same counts are fine there.
    assert request_for(FocusMove(1, 0x9000), EVI_D70) == codec_requests.FocusDirect(0x9000)


def test_pan_tilt_degrees_and_speed_codes_come_from_the_camera_profile() -> None:
    absolute = PanTiltAbsolute(pan_deg=10.0, tilt_deg=-5.0, pan_speed=3, tilt_speed=2)
    d100 = request_for(absolute, EVI_D100)
    assert d100 == codec_requests.PanTiltAbsolute(3, 2, 144, -72)  # 14.4 counts/deg
    d70 = request_for(absolute, EVI_D70)
    assert isinstance(d70, codec_requests.PanTiltAbsolute)
    assert (d70.pan, d70.tilt) == (round(10.0 * 2267 / 170), round(-5.0 * 1200 / 90))
    with pytest.raises(ValueError, match="pan_deg"):
        request_for(PanTiltAbsolute(150.0, 0.0, 1, 1), EVI_D100)  # beyond ±100°
    drive = request_for(PanTiltDrive(-4, 0, -3.7, 0.0), EVI_D100)
    assert drive == codec_requests.PanTiltDrive(
        4, 1, codec_requests.PanDirection.LEFT, codec_requests.TiltDirection.STOP
    )  # a stopped axis still sends speed 01 (00 is a syntax error on some models)
    up = request_for(PanTiltDrive(2, 5, 2.4, 4.7), EVI_D100)
    assert up == codec_requests.PanTiltDrive(
        2, 5, codec_requests.PanDirection.RIGHT, codec_requests.TiltDirection.UP
    )
    with pytest.raises(ValueError):
        request_for(PanTiltDrive(1, 0x15, 2.0, 155.0), EVI_D100)  # tilt codes end at 0x14
    assert request_for(PanTiltStop(), EVI_D100) == codec_requests.PanTiltDrive.stop()
    assert request_for(PanTiltInquiry(), EVI_D100) == codec_requests.PanTiltPositionInquiry()


def test_completion_timeouts_follow_the_profile() -> None:
    focus = completion_timeout_s(codec_requests.FocusDirect(0x3000), EVI_D100, 1.0)
    assert focus == pytest.approx(EVI_D100.focus_full_travel_s * 1.25 + 1.0)
    slow = completion_timeout_s(codec_requests.PanTiltAbsolute(1, 1, 0, 0), EVI_D100, 1.0)
    fast = completion_timeout_s(codec_requests.PanTiltAbsolute(0x18, 0x14, 0, 0), EVI_D100, 1.0)
    assert slow is not None
    assert fast is not None
    assert slow == pytest.approx(200.0 / 2.0 * 1.25 + 1.0)  # the whole pan range at 2 °/s
    assert fast < slow
    assert completion_timeout_s(codec_requests.PanTiltDrive.stop(), EVI_D100, 1.0) is None


def test_outcomes_reach_the_right_scheduler_callbacks() -> None:
    rec = _Recorder()
    sched: Any = rec
    report_done(sched, FocusMove(4, 0x3000), 1.0, None, EVI_D100)
    report_done(sched, FocusInquiry(), 2.0, codec_replies.FocusPosition(0x3001), EVI_D100)
    report_done(sched, PanTiltInquiry(), 3.0, codec_replies.PanTiltPosition(144, -72), EVI_D100)
    report_done(sched, PanTiltStop(), 4.0, None, EVI_D100)
    report_failed(sched, FocusMove(5, 0x3000), 5.0)
    report_failed(sched, FocusInquiry(), 6.0)
    report_failed(sched, PanTiltDrive(1, 0, 2.0, 0.0), 7.0)
    assert rec.calls == [
        ("on_focus_completed", 4, 1.0),
        ("on_focus_position", 2.0, 0x3001),
        ("on_pan_tilt_position", 3.0, 10.0, -5.0),
        ("on_pan_tilt_done", 3.0),
        ("on_pan_tilt_done", 4.0),
        ("on_focus_failed", 5, 5.0),
        ("on_focus_inquiry_failed", 6.0),
        ("on_pan_tilt_failed", 7.0),
    ]
    with pytest.raises(TypeError):
        report_done(sched, FocusInquiry(), 8.0, None, EVI_D100)


async def _outcome(rec: _Recorder, count: int) -> None:
    assert rec.event is not None
    async with asyncio.timeout(WAIT_S):
        while len(rec.calls) < count:
            rec.event.clear()
            await rec.event.wait()


async def test_the_daemon_actuators_run_actions_on_the_simulated_camera() -> None:
    rec = _Recorder()
    sched: Any = rec
    outcomes = 0

    def woken() -> None:
        nonlocal outcomes
        outcomes += 1

    async with sim_camera(DeviceConfig(autofocus_at_power_up=False)) as (_server, _link, camera):
        actuators = Actuators(camera, sched, woken, clock=lambda: 42.0)
        async with asyncio.TaskGroup() as group:
            tasks = [
                group.create_task(actuators.run_focus()),
                group.create_task(actuators.run_pan_tilt()),
            ]
            actuators.dispatch(FocusMove(9, 0x3000))
            actuators.dispatch(PanTiltAbsolute(10.0, -5.0, 0x18, 0x14))
            await _outcome(rec, 2)
            actuators.dispatch(FocusInquiry())
            actuators.dispatch(PanTiltInquiry())
            await _outcome(rec, 5)
            actuators.dispatch(FocusMove(10, 0x0100))  # outside the D100's focus range
            await _outcome(rec, 6)
            for task in tasks:
                task.cancel()
    assert set(rec.calls[:2]) == {("on_focus_completed", 9, 42.0), ("on_pan_tilt_done", 42.0)}
    answers = sorted(rec.calls[2:5], key=lambda call: call[0])
    assert answers[0] == ("on_focus_position", 42.0, 0x3000)
    assert answers[1] == ("on_pan_tilt_done", 42.0)
    name, t, pan, tilt = answers[2]
    assert (name, t) == ("on_pan_tilt_position", 42.0)
    assert (pan, tilt) == (pytest.approx(10.0), pytest.approx(-5.0))  # counts / 14.4
    assert rec.calls[5] == ("on_focus_failed", 10, 42.0)
    assert actuators.focus_failures == 1
    assert outcomes == 5
