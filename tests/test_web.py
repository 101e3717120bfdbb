"""The dashboard server: token rule, command path, /metrics, video and events streams."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import cv2
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from dffd.mqtt import models
from dffd.mqtt.latency import make_estimate
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics
from dffd.web.interface import (
    CallbackSource,
    DashboardFeed,
    DashboardSource,
    FrameView,
    Overlay,
)
from dffd.web.overlay import annotate, normals
from dffd.web.server import (
    DashboardServer,
    WebConfigError,
    WebSettings,
    is_loopback,
    parse_listen,
    read_token,
)
from tests.web_support import HEIGHT, WIDTH, StaticSource, SyntheticDaemon

TOKEN = "0123456789abcdef0123456789abcdef"
# Generous bound for one message of a stream that produces several per second.
STREAM_TIMEOUT_S = 10.0
# The synthetic daemon acquires the disc on its first frames and publishes estimates at once.
FIRST_ESTIMATES_TIMEOUT_S = 10.0


@pytest.fixture
async def daemon() -> AsyncIterator[SyntheticDaemon]:
    d = SyntheticDaemon(asyncio.get_running_loop())
    d.start()
    try:
        yield d
    finally:
        d.stop()


@pytest.fixture
async def server(daemon: SyntheticDaemon) -> AsyncIterator[DashboardServer]:
    async with DashboardServer(WebSettings("127.0.0.1", 0), daemon, daemon.metrics) as srv:
        yield srv


# -- settings and the token rule --------------------------------------------------------------


def test_listen_parsing_and_loopback() -> None:
    assert parse_listen("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_listen("[::1]:9000") == ("::1", 9000)
    assert parse_listen("0.0.0.0:0") == ("0.0.0.0", 0)
    for bad in ("8080", ":8080", "host:port", "127.0.0.1:70000"):
        with pytest.raises(WebConfigError, match=r"web\.listen"):
            parse_listen(bad)
    assert is_loopback("127.0.0.1")
    assert is_loopback("127.1.2.3")
    assert is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    assert not is_loopback("192.168.1.10")
    assert not is_loopback("camera-pc.lab")


def test_non_loopback_without_token_is_refused(tmp_path: Path) -> None:
    with pytest.raises(WebConfigError, match=r"not a loopback address.*token_file"):
        WebSettings.from_values("0.0.0.0:8080")
    with pytest.raises(WebConfigError, match="not a loopback"):
        DashboardServer(WebSettings("192.168.1.10", 8080), StaticSource())
    short = tmp_path / "short"
    short.write_text("secret\n")
    with pytest.raises(WebConfigError, match="at least 16"):
        WebSettings.from_values("0.0.0.0:8080", short)
    with pytest.raises(WebConfigError, match="cannot be read"):
        read_token(tmp_path / "missing")
    good = tmp_path / "token"
    good.write_text(f"  {TOKEN}\n")
    settings = WebSettings.from_values("0.0.0.0:8080", good)
    assert settings.token == TOKEN
    assert WebSettings.from_values("127.0.0.1:8080").token is None


async def test_token_required_when_set_header_or_cookie() -> None:
    source = StaticSource()
    # Bound to every interface: allowed because a token is set; reached over loopback.
    async with (
        DashboardServer(WebSettings("0.0.0.0", 0, token=TOKEN), source) as srv,
        aiohttp.ClientSession() as http,
    ):
        base = f"http://127.0.0.1:{srv.port}"
        for path in ("/", "/api/status", "/metrics", "/static/app.js"):
            async with http.get(base + path) as r:
                assert r.status == 401, path
                assert r.headers["WWW-Authenticate"].startswith("Bearer")
                assert "bearer token is required" in await r.text()
        async with http.get(base + "/metrics", headers={"Authorization": "Bearer wrong"}) as r:
            assert r.status == 401
        async with http.post(
            base + "/api/command", json={"cmd": "release"}, headers={"Origin": base}
        ) as r:
            assert r.status == 401
        assert source.replies == []
        async with http.get(base + "/metrics", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
            assert r.status == 200
        # The browser path: /?token= sets an HttpOnly cookie and drops the token from the URL.
        async with http.get(base + "/?token=wrong", allow_redirects=False) as r:
            assert r.status == 401
        async with http.get(base + f"/?token={TOKEN}", allow_redirects=False) as r:
            assert r.status == 302
            assert r.headers["Location"] == "/"
            cookie = r.cookies["dffd_token"]
            assert cookie["httponly"]
            assert cookie["samesite"] == "Strict"
        async with http.get(base + "/api/status", cookies={"dffd_token": TOKEN}) as r:
            assert r.status == 200
            assert (await r.json())["bursts_rejected"] == 12


async def test_loopback_without_token_needs_none(server: DashboardServer) -> None:
    async with aiohttp.ClientSession() as http, http.get(server.url + "/") as r:
        assert r.status == 200
        page = await r.text()
    assert '<canvas id="video"' in page
    assert "http" not in page.replace("http-equiv", "")  # nothing loaded from elsewhere
    # DNS rebinding: another name pointed at 127.0.0.1 is not let in without a token.
    async with (
        aiohttp.ClientSession() as http,
        http.get(server.url + "/api/status", headers={"Host": f"evil.example:{server.port}"}) as r,
    ):
        assert r.status == 403
    async with (
        aiohttp.ClientSession() as http,
        http.get(server.url + "/api/status", headers={"Host": f"localhost:{server.port}"}) as r,
    ):
        assert r.status == 200


# -- commands ---------------------------------------------------------------------------------


async def test_commands_take_the_mqtt_path_with_the_same_replies(
    server: DashboardServer, daemon: SyntheticDaemon
) -> None:
    reference = Publisher(
        PublisherSettings(host="127.0.0.1", port=1), Topics("dffd", "x"),
        on_command=daemon.publisher._on_command,
    )  # fmt: skip
    url = server.url + "/api/command"
    origin = {"Origin": server.url}
    cases = [
        (b'{"cmd": "acquire", "roi": [10, 10, 0, 5], "id": 7}', 400),
        (b'{"cmd": "fly"}', 400),
        (b"not json", 400),
        (b'{"cmd": "acquire", "roi": [300, 200, 100, 100], "id": "big"}', 400),
        (b'{"cmd": "set_known_size", "size_m": 0.07, "id": 3}', 200),
    ]
    async with aiohttp.ClientSession() as http:
        for body, status in cases:
            headers = {"Content-Type": "application/json", **origin}
            async with http.post(url, data=body, headers=headers) as r:
                assert r.status == status, body
                got = await r.json()
            want = (await reference.execute(body)).model_dump(mode="json", by_alias=True)
            got.pop("t")
            want.pop("t")
            assert got == want, body
        async with http.post(
            url, json={"cmd": "acquire", "roi": [100, 60, 120, 120], "id": "w"}, headers=origin
        ) as r:
            assert r.status == 200
            reply = await r.json()
        assert reply == {
            "schema": 1, "id": "w", "cmd": "acquire", "ok": True, "error": None,
            "result": {"roi": [100, 60, 120, 120]}, "t": reply["t"],
        }  # fmt: skip
        assert daemon.acquires[-1] == (100, 60, 120, 120)
        # Not JSON-typed (a plain HTML form) or from another site's page: refused, not run.
        n = len(daemon.acquires)
        async with http.post(url, data=b'{"cmd": "release"}', headers=origin) as r:
            assert r.status == 415
        async with http.post(
            url, json={"cmd": "acquire", "roi": [0, 0, 10, 10]},
            headers={"Origin": "http://evil.example"},
        ) as r:  # fmt: skip
            assert r.status == 403
        assert len(daemon.acquires) == n


# -- metrics ----------------------------------------------------------------------------------


async def test_metrics_scrape_parses_and_holds_the_figures() -> None:
    source = StaticSource()
    srv = DashboardServer(WebSettings("127.0.0.1", 0), source)
    for latency in (0.004, 0.008, 0.012, 0.6):
        srv.metrics.observe_publish_latency(latency)
    for cpu in (0.0004, 0.0007, 0.003):
        srv.metrics.observe_frame_cpu(cpu)
    async with srv, aiohttp.ClientSession() as http, http.get(srv.url + "/metrics") as r:
        assert r.status == 200
        assert r.headers["Content-Type"].startswith("text/plain")
        text = await r.text()
    samples: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value

    def value(name: str, **labels: str) -> float:
        return samples[(name, tuple(sorted(labels.items())))]

    assert value("dffd_frame_rate_hz") == 29.5
    assert value("dffd_estimate_rate_hz") == 21.25
    assert value("dffd_depth_rate_hz") == 2.5
    assert value("dffd_depth_rate_limit_hz") == 3.75
    assert value("dffd_state", state="tracking") == 1
    assert value("dffd_state", state="idle") == 0
    assert value("dffd_last_estimate_age_seconds") == 0.25
    assert value("dffd_link_errors_total") == 3
    assert value("dffd_link_timeouts_total") == 4
    assert value("dffd_link_reconnects_total") == 5
    assert value("dffd_link_connected") == 1
    assert value("dffd_mqtt_connected") == 0
    assert value("dffd_mqtt_backlog_messages") == 42
    assert value("dffd_mqtt_reconnects_total") == 6
    for queue, n in (("frames", 7), ("publish_queue", 8), ("backlog", 9), ("log", 10)):
        assert value("dffd_dropped_total", queue=queue) == n
    assert value("dffd_bursts_total", outcome="accepted") == 11
    assert value("dffd_bursts_total", outcome="rejected") == 12
    assert value("dffd_publish_latency_seconds_count") == 4
    assert value("dffd_publish_latency_seconds_bucket", le="0.01") == 2
    assert value("dffd_publish_latency_seconds_bucket", le="0.5") == 3
    assert value("dffd_publish_latency_seconds_sum") == pytest.approx(0.624)
    assert value("dffd_core_cpu_seconds_count") == 3
    assert value("dffd_core_cpu_seconds_bucket", le="0.001") == 2


# -- video ------------------------------------------------------------------------------------


def test_overlay_draws_contour_centroid_and_bracket() -> None:
    image = np.full((240, 320), 40, np.uint8)
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    contour = np.stack((160 + 40 * np.cos(angles), 120 + 40 * np.sin(angles)), axis=1)
    n = normals(contour)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    # outward on a counter-clockwise circle in image coordinates: ±radial, same sign everywhere
    radial = (contour - [160, 120]) / 40
    dots = np.sum(n * radial, axis=1)
    assert np.all(np.abs(np.abs(dots) - 1) < 0.01)
    assert np.all(np.sign(dots) == np.sign(dots[0]))
    overlay = Overlay(
        state="tracking", contour_px=contour, normal_half_px=8, centroid_px=(160.0, 120.0),
        roi=(100, 60, 120, 120), focus_counts=0x5000, bracket_counts=(0x4000, 0x5000, 0x6000),
        counts_range=(0x1000, 0x8400), z_m=2.5, sigma_m=0.01,
    )  # fmt: skip
    out = annotate(FrameView(1, 0.0, image, overlay))
    assert out.shape == (240, 320, 3)
    assert image.max() == 40  # the frame itself is untouched
    changed = np.any(out != 40, axis=2)
    x, y = np.rint(contour[0]).astype(int)
    assert changed[y - 1 : y + 2, x - 1 : x + 2].any()  # the contour
    assert changed[120, 150:171].sum() >= 10  # the centroid cross
    assert changed[60, 100:221].sum() > 100  # the ROI's top edge
    assert changed[16:224, 294:305].sum() > 100  # the focus bracket bar on the right


def test_overlay_caption_sits_on_a_solid_box() -> None:
    # a thick black copy of the label under the thin one drifted off it (Hershey glyphs advance
    # by their stroke): the caption's background is one dark box, nothing of it beyond
    image = np.full((240, 320), 128, np.uint8)
    overlay = Overlay(state="tracking", z_m=9.752, sigma_m=0.013)
    out = annotate(FrameView(1, 0.0, image, overlay))
    band = np.any(out[:, :, :] != 128, axis=2)[:28]
    cols = np.flatnonzero(band.any(axis=0))
    rows = np.flatnonzero(band.any(axis=1))
    box = out[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    assert np.all(band[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1])  # no gray in the box
    assert box.mean() < 60  # dark, with light text on it
    assert box.max() > 200


async def _read_frames(ws: aiohttp.ClientWebSocketResponse, n: int) -> list[np.ndarray]:
    frames = []
    async with asyncio.timeout(STREAM_TIMEOUT_S):
        while len(frames) < n:
            msg = await ws.receive()
            assert msg.type == aiohttp.WSMsgType.BINARY
            img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
            assert img is not None
            frames.append(img)
    return frames


async def test_video_over_websocket_changes_and_is_encoded_only_when_watched(
    server: DashboardServer, daemon: SyntheticDaemon
) -> None:
    # Frames flow from the daemon, but nobody watches: nothing is encoded.
    async with asyncio.timeout(STREAM_TIMEOUT_S):
        await daemon.frames_flowing.wait()
    assert server.video.encoded == 0
    async with aiohttp.ClientSession() as http, http.ws_connect(server.url + "/ws/video") as ws:
        frames = await _read_frames(ws, 4)
    assert all(f.shape == (HEIGHT, WIDTH, 3) for f in frames)
    assert any(not np.array_equal(frames[0], f) for f in frames[1:])
    # The overlay is on the image: the contour colour (yellow-ish: B low, G and R high) appears.
    last = frames[-1].astype(int)
    assert np.any((last[:, :, 0] < 100) & (last[:, :, 1] > 150) & (last[:, :, 2] > 200))
    async with asyncio.timeout(STREAM_TIMEOUT_S):
        await server.video.wait_no_viewers()
    encoded = server.video.encoded
    await asyncio.sleep(0.3)
    assert server.video.encoded <= encoded + 1  # stops once the viewer left


async def test_mjpeg_stream(server: DashboardServer) -> None:
    async with aiohttp.ClientSession() as http, http.get(server.url + "/video.mjpeg") as r:
        assert r.headers["Content-Type"].startswith("multipart/x-mixed-replace")
        async with asyncio.timeout(STREAM_TIMEOUT_S):
            head = await r.content.readuntil(b"\r\n\r\n")
            assert b"Content-Type: image/jpeg" in head
            length = int(head.split(b"Content-Length: ")[1].split(b"\r\n")[0])
            jpeg = await r.content.readexactly(length)
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (HEIGHT, WIDTH, 3)


# -- events -----------------------------------------------------------------------------------


async def test_events_stream_estimates_and_status(server: DashboardServer) -> None:
    seqs: list[int] = []
    statuses = []
    async with aiohttp.ClientSession() as http, http.ws_connect(server.url + "/ws/events") as ws:
        async with asyncio.timeout(FIRST_ESTIMATES_TIMEOUT_S):
            hello = json.loads((await ws.receive()).data)
            assert hello["type"] == "hello"
            seqs += [p["seq"] for p in hello["points"]]
            while len(seqs) < 20 or not statuses:
                msg = json.loads((await ws.receive()).data)
                if msg["type"] == "estimates":
                    seqs += [p["seq"] for p in msg["points"]]
                    point = msg["points"][-1]
                    assert set(point["d"]) == {"measured", "cf1", "cf2", "lpv", "kf"}
                    assert point["truth"] == pytest.approx(5.0, abs=0.51)
                elif msg["type"] == "status":
                    statuses.append(msg["status"])
    assert seqs == sorted(set(seqs))  # each estimate once, in order
    assert statuses[-1]["status"]["camera"] == "web-test"
    assert statuses[-1]["frame_size"] == [WIDTH, HEIGHT]


def test_feed_is_bounded_and_keeps_only_rejections(daemon: SyntheticDaemon) -> None:
    assert isinstance(daemon, DashboardSource)
    feed = DashboardFeed(history_max=3, rejections_max=2)
    for seq in range(1, 6):
        feed.add_estimate(make_estimate(seq, float(seq)), truth_z_m=2.0)
    assert [p.estimate.seq for p in feed.estimates_after(-1)] == [3, 4, 5]
    assert [p.estimate.seq for p in feed.estimates_after(4)] == [5]
    assert feed.estimates_after(5) == []
    fit = models.Fit(alpha=1.0, v_mm=31.5, residual=0.1, accepted=True)
    base = models.Measurement(
        seq=1, burst=1, t=0.0, t_mono=0.0, focus_counts=[1, 2, 3], costs=[1.0, 0.5, 1.0],
        fit=fit, z_m=2.0,
    )  # fmt: skip
    feed.add_measurement(base)
    for burst, reason in ((2, "alpha <= 0"), (3, "vertex outside"), (4, "residual")):
        rejected = models.Fit(alpha=-1.0, v_mm=None, residual=0.1, accepted=False, reason=reason)
        feed.add_measurement(base.model_copy(update={"burst": burst, "fit": rejected}))
    assert [(m.burst, m.fit.reason) for m in feed.rejections()] == [
        (3, "vertex outside"), (4, "residual"),
    ]  # fmt: skip


async def test_callback_source_is_a_dashboard_source() -> None:
    static = StaticSource()
    source = CallbackSource(static.snapshot, static.execute)
    assert isinstance(source, DashboardSource)
    assert source.snapshot() == static.snapshot()
    reply = await source.execute(b'{"cmd": "ping"}')
    assert reply.ok
    assert static.replies == [b'{"cmd": "ping"}']


# -- [web] in the service config ---------------------------------------------------------------


def test_web_config_listen_token_and_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dffd.config import ConfigError, load_config

    def config(text: str) -> Path:
        path = tmp_path / "dffd.toml"
        path.write_text(text, encoding="utf-8")
        return path

    assert load_config(config("")).web.listen is None  # a config file: off unless set
    assert load_config(None).web.listen == "127.0.0.1:8080"  # the embedded run: on, loopback
    with pytest.raises(ConfigError) as info:
        load_config(config('[web]\nlisten = "0.0.0.0:8080"\n'))
    assert any(p.startswith("web.token_file:") and "loopback" in p for p in info.value.problems)
    with pytest.raises(ConfigError) as info:
        load_config(config('[web]\nlisten = "8080"\n'))
    assert any(p.startswith("web.listen:") for p in info.value.problems)
    web = load_config(config('[web]\nlisten = "0.0.0.0:8443"\ntoken_file = "token"\n')).web
    assert web.token_file == tmp_path / "token"  # relative to the config file
    monkeypatch.setenv("DFFD_WEB__LISTEN", "127.0.0.1:18080")
    assert load_config(config("")).web.listen == "127.0.0.1:18080"
