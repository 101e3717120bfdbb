"""Network video: exposure-time estimation (pure) and the FFmpeg stream source over real sockets.

The stream source reads the simulated camera's MJPEG-over-HTTP server through OpenCV's FFmpeg
backend (real TCP, real JPEG encoding and decoding); a recorded file plays at its own rate with
its own timestamps; a stopped and restarted server is reconnected.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.capture import EndOfVideoError
from drivers.exposure import FIT_MIN_FRAMES, ExposureClock
from drivers.frames import Frame, FrameSourceError
from drivers.sim.config import load_sim_camera_config
from drivers.sim.resources import reference_camera_file
from drivers.sim.rig import SimCamera, build_sim_camera
from drivers.sim.video_server import SimVideoServer
from drivers.stream import StreamFrameSource, StreamSettings, redact
from tests.conftest import free_port

FPS = 30.0
# A frame of the 30 fps simulator reaches the reader in ~50 ms on an idle machine; 5 s covers
# FFmpeg's stream probe and a loaded 2-core machine.
FRAME_TIMEOUT_S = 5.0


# -- exposure clock (pure) ---------------------------------------------------------------------
def _arrivals(n: int, *, jitter_s: float, seed: int) -> list[tuple[float, float]]:
    """(true exposure time, arrival) pairs: 40 ms latency plus uniform jitter."""
    rng = np.random.default_rng(seed)
    t0 = 12345.0
    return [
        (t0 + k / FPS, t0 + k / FPS + 0.040 + float(rng.uniform(0, jitter_s))) for k in range(n)
    ]


def test_arrival_mode_subtracts_the_latency() -> None:
    clock = ExposureClock("arrival", latency_s=0.05)
    assert clock.stamp(100.0, 3.0) == pytest.approx(99.95)
    assert clock.using_stream is False


def test_stream_timestamps_remove_the_arrival_jitter() -> None:
    clock = ExposureClock("auto", latency_s=0.040 + 0.005)  # mean latency of the arrivals
    pairs = _arrivals(200, jitter_s=0.010, seed=1)
    errors = [clock.stamp(a, k / FPS) - t for k, (t, a) in enumerate(pairs)]
    assert clock.using_stream
    settled = np.abs(errors[FIT_MIN_FRAMES * 2 :])
    assert settled.max() < 0.002  # ±5 ms of arrival jitter, stamps within 2 ms
    arrival_only = [a - 0.045 - t for t, a in pairs]
    assert np.abs(arrival_only).max() > 0.004


def test_stream_clock_drift_is_followed() -> None:
    # The camera's clock runs 200 ppm fast: its timestamps advance 1.0002 s per local second.
    clock = ExposureClock("auto", latency_s=0.045)
    pairs = _arrivals(900, jitter_s=0.010, seed=2)
    errors = [clock.stamp(a, (t - pairs[0][0]) * 1.0002) - t for t, a in pairs]
    assert clock.using_stream
    assert np.abs(errors[-300:]).max() < 0.002


def test_invented_mjpeg_timestamps_are_not_used() -> None:
    # FFmpeg's 25 fps grid under a 30 fps MJPEG stream: 17 % slow, rejected in auto mode.
    clock = ExposureClock("auto", latency_s=0.045)
    pairs = _arrivals(100, jitter_s=0.010, seed=3)
    for k, (_t, a) in enumerate(pairs):
        assert clock.stamp(a, k / 25.0) == pytest.approx(a - 0.045)
    assert clock.using_stream is False
    forced = ExposureClock("stream", latency_s=0.0)
    for k, (_t, a) in enumerate(pairs):
        forced.stamp(a, k / 25.0)
    assert forced.using_stream is True


def test_a_timestamp_jump_restarts_the_fit() -> None:
    clock = ExposureClock("auto", latency_s=0.0)
    pairs = _arrivals(60, jitter_s=0.0, seed=4)
    for k, (_t, a) in enumerate(pairs[:30]):
        clock.stamp(a, k / FPS)
    assert clock.using_stream
    _t, a = pairs[30]
    assert clock.stamp(a, 0.0) == pytest.approx(a)  # backwards: refit from scratch
    assert clock.using_stream is False


def test_redact_hides_the_password() -> None:
    assert (
        redact("rtsp://admin:s3cr@t@10.0.0.5:554/video1") == "rtsp://admin:***@10.0.0.5:554/video1"
    )
    assert redact("http://10.0.0.5/video.mjpg") == "http://10.0.0.5/video.mjpg"
    assert redact("/tmp/file.avi") == "/tmp/file.avi"


# -- the stream source over real sockets -----------------------------------------------------
def _sim_rig() -> SimCamera:
    return build_sim_camera(load_sim_camera_config(reference_camera_file()))


def _settings(url: str, **kw: object) -> StreamSettings:
    defaults: dict[str, object] = {
        "fps": FPS,
        "latency_s": 0.0,
        "open_timeout_s": 3.0,
        "read_timeout_s": 1.0,
        "reconnect_initial_s": 0.05,
        "reconnect_max_s": 0.2,
        "queue_frames": 4,
    }
    return StreamSettings(url, **{**defaults, **kw})  # type: ignore[arg-type]


async def test_mjpeg_over_http_delivers_the_simulated_frames() -> None:
    rig = _sim_rig()
    async with SimVideoServer(rig.source) as server:
        source = StreamFrameSource(_settings(server.url))
        await source.start()
        try:
            assert source.frame_size == (640, 480)
            frames = [
                await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S) for _ in range(20)
            ]
        finally:
            await source.close()
    assert [f.index for f in frames] == list(range(20))
    assert all(f.image.shape == (480, 640) and f.image.dtype == np.uint8 for f in frames)
    health = source.health()
    assert health.frames >= 20
    assert health.reconnects == 0
    assert health.stream_timestamps is False  # MJPEG has none: arrival times
    # The last decoded frame is one of the simulated exposures of the 100 ms before its arrival:
    # re-rendered (same seeded noise), one of them matches it within JPEG's error, while two
    # different exposures differ by their independent read noise (~2.3 DN mean).
    last = frames[-1]
    recent = [
        tr.index
        for k in range(2000)
        if (tr := rig.source.truth_for(k)) is not None and last.t - 0.1 < tr.t < last.t
    ]
    diffs = [
        float(np.abs(rig.source.render_frame(k).image.astype(np.int16) - last.image).mean())
        for k in recent
        if k is not None
    ]
    assert min(diffs) < 1.5, diffs


async def test_a_lost_stream_is_reconnected_and_counted() -> None:
    port = free_port()
    rig = _sim_rig()
    server = SimVideoServer(rig.source, port=port)
    await server.start()
    source = StreamFrameSource(_settings(server.url))
    await source.start()
    try:
        first = await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S)
        await server.stop()  # the camera goes away
        # Drain what was buffered; then nothing comes until the camera is back.
        with pytest.raises(TimeoutError):
            await _drain(source, 0.5)
        assert source.health().connected is False
        again = SimVideoServer(_sim_rig().source, port=port)
        await again.start()
        try:
            frame = await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S)
        finally:
            await again.stop()
    finally:
        await source.close()
    assert frame.index > first.index  # indices continue across the reconnect
    assert source.reconnects == 1
    assert source.health().reconnects == 1


async def test_a_video_file_plays_at_its_rate_with_its_timestamps(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (160, 120))
    for k in range(20):
        image = np.full((120, 160, 3), 40, np.uint8)
        cv2.circle(image, (20 + 4 * k, 60), 10, (200, 200, 200), -1)
        writer.write(image)
    writer.release()
    source = StreamFrameSource(_settings(str(path)))
    await source.start()
    frames = []
    try:
        with pytest.raises(EndOfVideoError):
            await _drain(source, FRAME_TIMEOUT_S, frames)
    finally:
        await source.close()
    assert len(frames) == 20
    assert source.fps == pytest.approx(FPS)
    assert source.health().stream_timestamps is True
    steps = np.diff([f.t for f in frames])
    assert np.allclose(steps, 1 / FPS, atol=1e-6)  # the file's own timeline


async def test_an_unreachable_stream_says_what_to_check() -> None:
    url = f"http://127.0.0.1:{free_port()}/video.mjpg"
    source = StreamFrameSource(_settings(url, open_timeout_s=1.0))
    with pytest.raises(FrameSourceError, match=r"cannot open video stream .*127\.0\.0\.1"):
        await source.start()
    await source.close()


async def _drain(
    source: StreamFrameSource, timeout_s: float, into: list[Frame] | None = None
) -> None:
    """Take frames until one does not come within ``timeout_s`` (or the source ends)."""
    while True:
        frame = await asyncio.wait_for(source.next_frame(), timeout_s)
        if into is not None:
            into.append(frame)


# -- configuration -----------------------------------------------------------------------------
def test_stream_config_needs_a_url_and_a_real_camera() -> None:
    from dffd.config import DffdConfig

    with pytest.raises(ValueError, match=r"required when capture\.source is 'stream'"):
        DffdConfig.model_validate(
            {"camera": {"driver": "visca", "port": "/dev/null"}, "capture": {"source": "stream"}}
        )
    with pytest.raises(ValueError, match=r"sim\.video = 'http'"):
        DffdConfig.model_validate({"capture": {"source": "stream", "url": "http://x/v.mjpg"}})
    cfg = DffdConfig.model_validate(
        {
            "camera": {"driver": "visca", "port": "visca-ip://10.0.0.5"},
            "capture": {"source": "stream", "url": "rtsp://10.0.0.5/video1", "fps": 25.0},
        }
    )
    assert cfg.capture.latency == pytest.approx(1 / 25)  # latency_frames = 1 by default
    cfg = DffdConfig.model_validate(
        {"camera": {"driver": "visca", "port": "/dev/null"},
         "capture": {"source": "stream", "url": "x.avi", "latency_s": 0.12}}
    )  # fmt: skip
    assert cfg.capture.latency == pytest.approx(0.12)


async def test_sim_camera_cli_serves_visca_ip_and_mjpeg_video() -> None:
    # `dffd sim-camera --listen udp://… --video http://…`: the control address and the video URL
    # on its first two stdout lines; the frames show what the VISCA commands do (a pan moves
    # the target across the image).
    import sys

    from drivers.visca.camera import Camera
    from drivers.visca.link import ViscaLink

    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "dffd", "sim-camera", "--listen", "udp://127.0.0.1:0",
        "--video", "http://127.0.0.1:0",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        control = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
        video = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
        assert control.startswith("visca-ip://127.0.0.1:")
        assert video.startswith("http://127.0.0.1:")
        assert video.strip().endswith("/video.mjpg")
        source = StreamFrameSource(_settings(video.strip()))
        await source.start()
        try:
            async with ViscaLink(control.strip()) as link:
                camera = Camera(link, 1)
                await camera.initialize()
                before = await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S)
                await camera.pan_tilt_absolute(0.3, 0.0)
                await _drain_for(source, 0.3)
                after = await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S)
        finally:
            await source.close()
    finally:
        if proc.returncode is None:
            proc.terminate()
        await asyncio.wait_for(proc.wait(), 10)
    assert proc.returncode == 0
    # Panning right moves the (bright) target left in the image.
    assert _bright_centroid_x(after.image) < _bright_centroid_x(before.image) - 5


async def _drain_for(source: StreamFrameSource, seconds: float) -> None:
    """Skip the frames of the next ``seconds`` (those exposed during the move)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end:
        await asyncio.wait_for(source.next_frame(), FRAME_TIMEOUT_S)


def _bright_centroid_x(image: np.ndarray) -> float:
    _ys, xs = np.nonzero(image > 120)
    assert xs.size > 0
    return float(xs.mean())


def test_the_ip_camera_example_config_loads() -> None:
    from dffd.config import load_config

    config = load_config(Path(__file__).resolve().parent.parent / "config" / "lab-ip-camera.toml")
    assert config.camera.port == "visca-ip://192.168.0.100:52381"
    assert config.camera.model == "srg-300"
    assert config.capture.source == "stream"
    assert config.capture.latency == pytest.approx(0.12)
