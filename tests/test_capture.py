"""The OpenCV frame source: a real video file written here, fake devices for the failure paths."""

from __future__ import annotations

import asyncio
import itertools
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.capture import (
    CaptureSettings,
    EndOfVideoError,
    FrameHandoff,
    OpenCVFrameSource,
    backoff_delays,
)
from drivers.frames import Frame, FrameSource, FrameSourceError

FRAME_TIMEOUT_S = 5.0  # generous: a frame from a local file or a fake arrives in well under 1 s
N_FRAMES = 12
SIZE = (160, 120)


def _level(i: int) -> int:
    return 20 + 15 * i


@pytest.fixture
def video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, SIZE)
    assert writer.isOpened()
    for i in range(N_FRAMES):
        writer.write(np.full((SIZE[1], SIZE[0], 3), _level(i), dtype=np.uint8))
    writer.release()
    return path


async def _next(source: OpenCVFrameSource) -> Frame:
    async with asyncio.timeout(FRAME_TIMEOUT_S):
        return await source.next_frame()


async def test_video_file_frames_arrive_in_order_with_monotonic_timestamps(video: Path) -> None:
    source = OpenCVFrameSource(CaptureSettings(device=str(video), queue_frames=64))
    assert isinstance(source, FrameSource)
    await source.start()
    try:
        frames = [await _next(source) for _ in range(N_FRAMES)]
        with pytest.raises(EndOfVideoError):
            await _next(source)
    finally:
        await source.close()
    await source.close()  # idempotent
    assert [f.index for f in frames] == list(range(N_FRAMES))
    assert all(b.t > a.t for a, b in itertools.pairwise(frames))
    assert all(f.image.shape == (SIZE[1], SIZE[0]) and f.image.dtype == np.uint8 for f in frames)
    levels = [float(f.image.mean()) for f in frames]
    assert levels == pytest.approx([_level(i) for i in range(N_FRAMES)], abs=3.0)
    assert source.frame_size == SIZE
    assert source.fps == pytest.approx(30.0)
    assert source.dropped_frames == 0


async def test_bgr_output_and_latency_correction(video: Path) -> None:
    ticks = itertools.count(start=100.0, step=1.0 / 30.0)
    source = OpenCVFrameSource(
        CaptureSettings(device=str(video), gray=False, latency_s=0.05, queue_frames=64),
        clock=lambda: next(ticks),
    )
    await source.start()
    try:
        first = await _next(source)
    finally:
        await source.close()
    assert first.image.shape == (SIZE[1], SIZE[0], 3)
    assert first.t == pytest.approx(100.0 - 0.05)


async def test_missing_device_gives_a_clear_error(tmp_path: Path) -> None:
    source = OpenCVFrameSource(CaptureSettings(device=str(tmp_path / "no-such-video0")))
    with pytest.raises(FrameSourceError, match="cannot open video source"):
        await source.start()
    with pytest.raises(FrameSourceError, match="not started"):
        await source.next_frame()


class FakeCapture:
    """A device that yields ``frames`` frames, then fails reads (or blocks until released)."""

    def __init__(self, frames: int, *, opened: bool = True, block: threading.Event | None = None):
        self._left = frames
        self._opened = opened
        self._block = block
        self.exhausted = threading.Event()
        self.props: dict[int, float] = {}

    def isOpened(self) -> bool:
        return self._opened

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self._left > 0:
            self._left -= 1
            return True, np.full((4, 6, 3), 100, dtype=np.uint8)
        self.exhausted.set()
        if self._block is not None:
            self._block.wait(FRAME_TIMEOUT_S)
        return False, None

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return {
            cv2.CAP_PROP_FRAME_WIDTH: 6.0,
            cv2.CAP_PROP_FRAME_HEIGHT: 4.0,
            cv2.CAP_PROP_FPS: 30.0,
        }.get(prop, 0.0)

    def release(self) -> None:
        self._opened = False


async def test_device_properties_are_requested_for_v4l2() -> None:
    fake = FakeCapture(1)
    opened: list[tuple[object, int]] = []

    def factory(device: str | int, backend: int) -> FakeCapture:
        opened.append((device, backend))
        return fake

    source = OpenCVFrameSource(
        CaptureSettings(device="/dev/video7", fourcc="YUYV", reopen_initial_s=60.0),
        capture_factory=factory,
    )
    await source.start()
    await _next(source)
    await source.close()
    assert opened == [("/dev/video7", cv2.CAP_V4L2)]
    assert fake.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc(*"YUYV")
    assert fake.props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert fake.props[cv2.CAP_PROP_FRAME_WIDTH] == 640
    assert source.frame_size == (6, 4)  # what the driver granted


async def test_lost_device_is_reopened_and_frames_continue() -> None:
    devices = [FakeCapture(3), FakeCapture(0, opened=False), FakeCapture(3)]
    calls = iter(devices)
    source = OpenCVFrameSource(
        CaptureSettings(device=0, queue_frames=64, reopen_initial_s=0.001, reopen_max_s=0.002),
        capture_factory=lambda device, backend: next(calls, FakeCapture(0, opened=False)),
    )
    await source.start()
    try:
        frames = [await _next(source) for _ in range(6)]
    finally:
        await source.close()
    assert [f.index for f in frames] == list(range(6))
    assert source.reopen_count == 1  # the second open failed and was retried
    assert frames[0].image.ndim == 2  # converted to gray


async def test_slow_consumer_gets_the_newest_frames_and_drops_are_counted() -> None:
    unblock = threading.Event()
    fake = FakeCapture(10, block=unblock)
    source = OpenCVFrameSource(
        CaptureSettings(device=0, queue_frames=2, reopen_initial_s=60.0),
        capture_factory=lambda device, backend: fake,
    )
    await source.start()
    try:
        assert await asyncio.to_thread(fake.exhausted.wait, FRAME_TIMEOUT_S)
        frames = [await _next(source), await _next(source)]
    finally:
        unblock.set()
        await source.close()
    assert [f.index for f in frames] == [8, 9]
    assert source.dropped_frames == 8


async def test_gaps_in_device_timestamps_count_as_dropped_frames() -> None:
    times = iter([0.0, 1 / 30, 2 / 30, 5 / 30, 6 / 30])  # frames 3 and 4 never came
    unblock = threading.Event()
    fake = FakeCapture(5, block=unblock)
    source = OpenCVFrameSource(
        CaptureSettings(device=0, queue_frames=64, reopen_initial_s=60.0),
        capture_factory=lambda device, backend: fake,
        clock=lambda: next(times, 1.0),
    )
    await source.start()
    try:
        frames = [await _next(source) for _ in range(5)]
    finally:
        unblock.set()
        await source.close()
    assert len(frames) == 5
    assert source.dropped_frames == 2


def test_handoff_drops_the_oldest() -> None:
    handoff = FrameHandoff(2)
    image = np.zeros((1, 1), dtype=np.uint8)
    assert [handoff.push(Frame(i, float(i), image)) for i in range(4)] == [False, False, True, True]
    assert handoff.dropped == 2
    assert [handoff.pop().index, handoff.pop().index] == [2, 3]  # type: ignore[union-attr]
    assert handoff.pop() is None


def test_backoff_doubles_up_to_the_cap() -> None:
    assert list(itertools.islice(backoff_delays(0.5, 3.0), 6)) == [0.5, 1.0, 2.0, 3.0, 3.0, 3.0]
