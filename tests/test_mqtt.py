"""MQTT interface: payload models, shipped schemas, and the Publisher against a real mosquitto."""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aiomqtt
import jsonschema
import pytest
from pydantic import ValidationError

from dffd.config import MqttSection
from dffd.mqtt import schemas
from dffd.mqtt.commands import CommandRejected
from dffd.mqtt.models import (
    Acquire,
    Command,
    CommandReply,
    DepthByEstimator,
    Estimate,
    Fit,
    Measurement,
    MqttHealth,
    Status,
    Truth,
    parse_command,
)
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics, qos, retained

from .conftest import Mosquitto, MosquittoFactory

# Broker round trips on loopback take milliseconds; 5 s absorbs a loaded CI machine.
MESSAGE_TIMEOUT_S = 5.0
# In the outage test the client retries exactly once per second, so a restarted broker and a
# fresh subscriber are both ready long before the client's next attempt.
OUTAGE_BACKOFF_S = 1.0
POLL_S = 0.01

SCHEMA_DIR = Path(__file__).resolve().parent.parent / "dffd" / "schemas"
TOPICS = Topics("dffd", "sim")


# -- helpers -----------------------------------------------------------------------------------


def estimate(seq: int, z: float = 2.0) -> Estimate:
    return Estimate(
        seq=seq,
        t=time.time(),
        t_mono=time.monotonic(),
        state="tracking",
        depth_m=DepthByEstimator(measured=None, cf1=None, cf2=z, lpv=z, kf=z),
        best="lpv",
        z_m=z,
        sigma_m=0.03,
        beta_m_s=0.001,
        size_m=0.0358,
        r_px=41.5,
        rho_per_s=-0.02,
        position_m=(0.1, -0.2, z),
        velocity_m_s=(0.0, 0.0, -0.1),
        pan_deg=1.5,
        tilt_deg=-0.5,
        focus_counts=0x4000,
    )


def measurement(seq: int) -> Measurement:
    return Measurement(
        seq=seq,
        burst=seq,
        t=time.time(),
        t_mono=time.monotonic(),
        focus_counts=[0x3000, 0x3400, 0x3800],
        v_mm=[4.31, 4.33, 4.35],
        costs=[0.9, 0.5, 0.8],
        fit=Fit(alpha=12.0, v_mm=4.332, residual=0.01, accepted=True),
        z_m=2.01,
        sigma_m=0.05,
    )


def settings(broker: Mosquitto, **overrides: Any) -> PublisherSettings:
    values: dict[str, Any] = {
        "host": broker.host,
        "port": broker.port,
        "keepalive_s": 5,
        "reconnect_min_s": 0.05,
        "reconnect_max_s": 0.2,
    } | overrides
    return PublisherSettings(**values)


async def wait_until(predicate: Callable[[], bool], timeout_s: float = MESSAGE_TIMEOUT_S) -> None:
    """Poll a counter that has no event of its own, bounded by ``timeout_s``."""
    async with asyncio.timeout(timeout_s):
        while not predicate():  # noqa: ASYNC110 - counters have no event; bounded by timeout
            await asyncio.sleep(POLL_S)


class Subscriber:
    """A plain aiomqtt client collecting messages of some topics into a queue."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.queue: asyncio.Queue[aiomqtt.Message] = asyncio.Queue()

    async def next(self, timeout_s: float = MESSAGE_TIMEOUT_S) -> aiomqtt.Message:
        async with asyncio.timeout(timeout_s):
            return await self.queue.get()

    async def next_json(self, topic: str | None = None) -> dict[str, Any]:
        while True:
            message = await self.next()
            if topic is None or message.topic.matches(topic):
                assert isinstance(message.payload, bytes)
                data: dict[str, Any] = json.loads(message.payload)
                return data

    async def _pump(self) -> None:
        try:
            async for message in self.client.messages:
                self.queue.put_nowait(message)
        except aiomqtt.MqttError:
            return  # the broker went away; the test decides what that means


@asynccontextmanager
async def subscribed(broker: Mosquitto, *topics: str) -> AsyncIterator[Subscriber]:
    nodelay = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)
    async with aiomqtt.Client(broker.host, broker.port, socket_options=nodelay) as client:
        for topic in topics:
            await client.subscribe(topic, qos=1)
        sub = Subscriber(client)
        pump = asyncio.create_task(sub._pump())
        try:
            yield sub
        finally:
            pump.cancel()
            await asyncio.gather(pump, return_exceptions=True)


def validate(kind: str, payload: dict[str, Any]) -> None:
    jsonschema.validate(payload, schemas.load(kind))  # type: ignore[arg-type]


# -- models and schemas ------------------------------------------------------------------------


def test_committed_schemas_equal_generated() -> None:
    generated = schemas.generate()
    committed = {path.name for path in SCHEMA_DIR.glob("*.schema.json")}
    assert committed == set(generated), "run: python -m dffd.mqtt.schemas --out dffd/schemas"
    for name, schema in generated.items():
        text = (SCHEMA_DIR / name).read_text(encoding="utf-8")
        assert text == schemas.render(schema), f"{name} is stale; regenerate the schemas"


def test_topics_follow_design_table() -> None:
    topics = Topics("lab", "evi1")
    assert topics.estimate == "lab/evi1/estimate"
    assert topics.measurement == "lab/evi1/measurement"
    assert topics.status == "lab/evi1/status"
    assert topics.cmd == "lab/evi1/cmd"
    assert topics.cmd_reply == "lab/evi1/cmd/reply"
    assert topics.sim_truth == "lab/evi1/sim/truth"
    assert (qos("status"), retained("status")) == (1, True)
    assert (qos("estimate"), retained("estimate")) == (0, False)
    assert (qos("cmd_reply"), retained("cmd_reply")) == (1, False)
    assert (qos("sim_truth"), retained("sim_truth")) == (0, False)


def test_payloads_validate_against_shipped_schemas() -> None:
    truth = Truth(t_mono=1.0, z_m=2.0, position_m=(0.0, 0.0, 2.0))
    reply = CommandReply(id="a", cmd="ping", ok=True, t=1.0)
    status = Status(availability="online", t=1.0, t_mono=1.0, version="0.1.0", state="tracking")
    cases = {
        "estimate": estimate(1),
        "measurement": measurement(1),
        "sim_truth": truth,
        "cmd_reply": reply,
        "status": status,
    }
    for kind, payload in cases.items():
        data = json.loads(payload.to_json())
        assert data["schema"] == 1
        validate(kind, data)
    # the schemas are strict: an unknown key or a missing key is rejected
    bad = json.loads(estimate(1).to_json()) | {"extra": 1}
    with pytest.raises(jsonschema.ValidationError):
        validate("estimate", bad)
    missing = json.loads(estimate(1).to_json())
    del missing["z_m"]
    with pytest.raises(jsonschema.ValidationError):
        validate("estimate", missing)


def test_models_reject_non_finite_and_inconsistent_values() -> None:
    with pytest.raises(ValidationError):
        estimate(1, z=math.nan)
    with pytest.raises(ValidationError, match="one entry per burst frame"):
        Measurement(
            seq=0,
            burst=0,
            t=0.0,
            t_mono=0.0,
            focus_counts=[1, 2, 3, 4],
            costs=[1.0, 2.0, 3.0],
            fit=Fit(alpha=None, v_mm=None, residual=None, accepted=False, reason="too few"),
            z_m=None,
        )


def test_command_parsing_and_schema() -> None:
    command = parse_command(b'{"cmd": "acquire", "id": 7, "roi": [10, 20, 30, 40]}')
    assert command == Acquire(cmd="acquire", id=7, roi=(10, 20, 30, 40))
    validate("cmd", {"cmd": "set_known_size", "size_m": None, "id": "x"})
    with pytest.raises(jsonschema.ValidationError):
        validate("cmd", {"cmd": "explode"})
    with pytest.raises(ValidationError):
        parse_command(b'{"cmd": "acquire", "roi": [0, 0, 0, 10]}')


def test_settings_from_config_reads_password(tmp_path: Path) -> None:
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n", encoding="utf-8")
    config = MqttSection(
        url="mqtts://broker.lab:8884", username="dffd", password_file=secret, ca_file=secret
    )
    s = PublisherSettings.from_config(config)
    assert (s.host, s.port, s.tls, s.username, s.password) == (
        "broker.lab",
        8884,
        True,
        "dffd",
        "s3cret",
    )


async def test_publish_never_blocks_and_drops_oldest_when_queue_full() -> None:
    # not running: nothing drains the queue, so it fills and the oldest go first
    publisher = Publisher(PublisherSettings("127.0.0.1", 1, queue_max_messages=5), TOPICS)
    for seq in range(12):
        publisher.publish(estimate(seq))
    stats = publisher.stats()
    assert stats.queue_dropped == 7
    assert publisher._outbox.qsize() == 5
    assert [publisher._outbox.get_nowait().payload.seq for _ in range(5)] == [7, 8, 9, 10, 11]  # type: ignore[union-attr]


def test_qos0_messages_paho_never_wrote_go_back_to_the_backlog_in_order() -> None:
    from paho.mqtt.client import MQTTMessageInfo

    from dffd.mqtt.publisher import _Outgoing

    publisher = Publisher(PublisherSettings("127.0.0.1", 1, backlog_max_messages=3), TOPICS)
    publisher._backlog.append(_Outgoing("estimate", estimate(9)))  # queued during the outage
    infos = [MQTTMessageInfo(mid) for mid in range(4)]
    infos[0]._set_as_published()  # written before the connection dropped
    for seq, info in enumerate(infos):
        publisher._unsent.append((info, _Outgoing("estimate", estimate(seq))))
    publisher._keep_unsent()
    # 1, 2, 3 were never written; the backlog holds 3: the oldest of them does not fit
    assert [o.payload.seq for o in publisher._backlog] == [2, 3, 9]  # type: ignore[union-attr]
    assert publisher.stats().backlog_dropped == 1
    assert not publisher._unsent


# -- against a real broker ---------------------------------------------------------------------


async def test_data_flows_with_retained_online_and_offline_status(mosquitto: Mosquitto) -> None:
    async with Publisher(settings(mosquitto), TOPICS) as publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        async with subscribed(mosquitto, f"{TOPICS.base}/#") as sub:
            status = await sub.next_json(TOPICS.status)  # retained, sent on connect
            assert status["availability"] == "online"
            validate("status", status)
            publisher.publish(estimate(1))
            publisher.publish(measurement(1))
            publisher.publish(Truth(t_mono=1.0, z_m=2.0, position_m=(0, 0, 2)))
            got = {}
            for kind, topic in (
                ("estimate", TOPICS.estimate),
                ("measurement", TOPICS.measurement),
                ("sim_truth", TOPICS.sim_truth),
            ):
                got[kind] = await sub.next_json(topic)
                validate(kind, got[kind])
            assert got["estimate"]["seq"] == 1
            assert got["estimate"]["replayed"] is False
            await publisher.stop()
            offline = await sub.next_json(TOPICS.status)
            assert offline["availability"] == "offline"
            assert offline["state"] is None
            validate("status", offline)
    # a newcomer sees the retained offline status
    async with subscribed(mosquitto, TOPICS.status) as late:
        message = await late.next()
        assert message.retain
        assert json.loads(message.payload)["availability"] == "offline"  # type: ignore[arg-type]


async def test_qos0_goes_out_within_publish_and_in_order(mosquitto: Mosquitto) -> None:
    async with Publisher(settings(mosquitto), TOPICS) as publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        async with subscribed(mosquitto, TOPICS.estimate) as sub:
            sent = publisher.stats().published
            publisher.publish(estimate(1))
            # handed to paho and written in the call: nothing waits in the outbox or in paho
            assert publisher.stats().published == sent + 1
            assert publisher._outbox.empty()
            assert not publisher._unsent
            # while the sender task holds a message, later ones queue behind it (order kept)
            publisher._sender_busy = True
            publisher.publish(estimate(2))
            assert publisher._outbox.qsize() == 1
            publisher._sender_busy = False
            publisher.publish(estimate(3))  # the outbox is not empty: queued too
            assert publisher._outbox.qsize() == 2
            seqs = [(await sub.next_json(TOPICS.estimate))["seq"] for _ in range(3)]
            assert seqs == [1, 2, 3]


async def test_a_status_sent_over_mqtt_says_mqtt_connected(mosquitto: Mosquitto) -> None:
    # The daemon builds its first status before the connection is up (connected false); what a
    # subscriber receives over that very connection must say connected (issue 13).
    before = Status(
        availability="online", t=time.time(), t_mono=time.monotonic(), version="0.1.0",
        state="acquiring", mqtt=MqttHealth(connected=False),
    )  # fmt: skip
    publisher = Publisher(settings(mosquitto), TOPICS)
    publisher.publish(before)
    async with publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        async with subscribed(mosquitto, TOPICS.status) as sub:
            first = await sub.next_json(TOPICS.status)  # the retained one, sent on connect
            assert first["availability"] == "online"
            assert first["mqtt"]["connected"] is True
            publisher.publish(before.model_copy(update={"t_mono": time.monotonic()}))
            queued = await sub.next_json(TOPICS.status)
            assert queued["mqtt"]["connected"] is True


async def test_last_will_marks_killed_client_offline(mosquitto: Mosquitto) -> None:
    script = (
        "import asyncio\n"
        "from dffd.mqtt.publisher import Publisher\n"
        "from dffd.mqtt.publisher_types import PublisherSettings\n"
        "from dffd.mqtt.topics import Topics\n"
        "async def main():\n"
        f"    s = PublisherSettings({mosquitto.host!r}, {mosquitto.port}, keepalive_s=5)\n"
        "    async with Publisher(s, Topics('dffd', 'sim')) as p:\n"
        "        await p.wait_connected()\n"
        "        print('connected', flush=True)\n"
        "        await asyncio.Event().wait()\n"
        "asyncio.run(main())\n"
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", script, stdout=asyncio.subprocess.PIPE
    )
    try:
        assert proc.stdout is not None
        async with asyncio.timeout(MESSAGE_TIMEOUT_S * 2):  # includes interpreter start-up
            assert await proc.stdout.readline() == b"connected\n"
        async with subscribed(mosquitto, TOPICS.status) as sub:
            assert (await sub.next_json())["availability"] == "online"
            proc.kill()  # no DISCONNECT: the broker must publish the will
            will = await sub.next_json()
            assert will["availability"] == "offline"
            assert "last will" in will["message"]
            validate("status", will)
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()


async def test_outage_backlog_is_bounded_and_replayed_flagged(mosquitto: Mosquitto) -> None:
    backlog_max = 10
    config = settings(
        mosquitto,
        backlog_max_messages=backlog_max,
        reconnect_min_s=OUTAGE_BACKOFF_S,
        reconnect_max_s=OUTAGE_BACKOFF_S,
    )
    async with Publisher(config, TOPICS) as publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        mosquitto.stop()
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_disconnected()
        for seq in range(25):
            publisher.publish(estimate(seq))
        publisher.publish(Truth(t_mono=1.0, z_m=2.0, position_m=(0, 0, 2)))  # not backlogged
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher._outbox.join()
        stats = publisher.stats()
        assert (stats.backlog, stats.backlog_dropped, stats.offline_dropped) == (10, 15, 1)
        # restart right after a failed attempt: the next attempt is a full backoff away
        failures = publisher.stats().connect_failures
        await wait_until(
            lambda: publisher.stats().connect_failures > failures, 3 * OUTAGE_BACKOFF_S
        )
        mosquitto.start()
        async with subscribed(mosquitto, TOPICS.estimate) as sub:
            async with asyncio.timeout(MESSAGE_TIMEOUT_S):
                await publisher.wait_connected()
            publisher.publish(estimate(100))
            received = [await sub.next_json() for _ in range(backlog_max + 1)]
    assert [m["seq"] for m in received] == [*range(15, 25), 100]
    assert all(m["replayed"] for m in received[:-1])
    assert received[-1]["replayed"] is False
    for m in received:
        validate("estimate", m)
    final = publisher.stats()
    assert final.replayed == backlog_max
    assert final.backlog == 0
    assert publisher.health().reconnects == 1


async def test_commands_get_replies_and_bad_ones_change_nothing(mosquitto: Mosquitto) -> None:
    executed: list[Command] = []

    async def handler(command: Command) -> dict[str, Any] | None:
        if isinstance(command, Acquire) and command.roi[0] > 600:
            raise CommandRejected("roi lies outside the 640×480 frame; choose x + w ≤ 640")
        if command.cmd == "home":
            raise RuntimeError("link exploded")
        executed.append(command)
        return {"accepted": True}

    async with Publisher(settings(mosquitto), TOPICS, on_command=handler) as publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        async with subscribed(mosquitto, TOPICS.cmd_reply) as sub:

            async def ask(payload: bytes) -> dict[str, Any]:
                await sub.client.publish(TOPICS.cmd, payload, qos=1)
                reply = await sub.next_json()
                validate("cmd_reply", reply)
                return reply

            ok = await ask(b'{"cmd": "acquire", "id": 1, "roi": [10, 20, 30, 40]}')
            assert (ok["id"], ok["ok"], ok["cmd"], ok["result"]) == (1, True, "acquire", {
                "accepted": True
            })  # fmt: skip
            ping = await ask(b'{"cmd": "ping", "id": "p"}')
            assert ping["ok"]
            assert ping["id"] == "p"
            assert "t_mono" in ping["result"]

            not_json = await ask(b"{nope")
            assert not not_json["ok"]
            assert "not JSON" in not_json["error"]
            assert not_json["id"] is None
            too_deep = await ask(b"[" * 100_000)
            assert not too_deep["ok"]
            assert "not JSON" in too_deep["error"]
            not_object = await ask(b"[1, 2]")
            assert not not_object["ok"]
            assert "JSON object" in not_object["error"]
            unknown = await ask(b'{"cmd": "self_destruct", "id": 2}')
            assert (unknown["id"], unknown["ok"]) == (2, False)
            assert "unknown command 'self_destruct'" in unknown["error"]
            assert "acquire" in unknown["error"]
            no_cmd = await ask(b'{"id": 3}')
            assert not no_cmd["ok"]
            assert 'missing "cmd"' in no_cmd["error"]
            bad_field = await ask(b'{"cmd": "acquire", "id": 4, "roi": [1, 2, 0, 4]}')
            assert not bad_field["ok"]
            assert "roi.2" in bad_field["error"]
            extra = await ask(b'{"cmd": "release", "id": 5, "force": true}')
            assert not extra["ok"]
            assert "force: unknown field" in extra["error"]
            size = await ask(b'{"cmd": "set_known_size", "id": 6, "size_m": -1}')
            assert not size["ok"]
            assert "size_m" in size["error"]
            rejected = await ask(b'{"cmd": "acquire", "id": 7, "roi": [620, 0, 30, 30]}')
            assert not rejected["ok"]
            assert "outside the 640" in rejected["error"]
            crashed = await ask(b'{"cmd": "home", "id": 8}')
            assert not crashed["ok"]
            assert "internal error" in crashed["error"]

            # still alive and serving after all that
            again = await ask(b'{"cmd": "release", "id": 9}')
            assert again["ok"]
    assert [c.cmd for c in executed] == ["acquire", "release"]
    stats = publisher.stats()
    assert (stats.commands, stats.commands_failed) == (13, 10)


# -- authentication and TLS --------------------------------------------------------------------


def _make_tls_files(directory: Path) -> tuple[Path, Path, Path]:
    """A throwaway CA and a server certificate for 127.0.0.1 (openssl CLI)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl is not installed (Debian package 'openssl')")
    ca_key, ca, key, csr, cert = (
        directory / n for n in ("ca.key", "ca.pem", "s.key", "s.csr", "s.pem")
    )
    san = directory / "san.ext"
    san.write_text("subjectAltName=IP:127.0.0.1\n")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    for args in (
        ["req", "-x509", *ec, "-keyout", ca_key, "-out", ca, "-days", "1",
         "-subj", "/CN=dffd-test-ca"],
        ["req", *ec, "-keyout", key, "-out", csr, "-subj", "/CN=127.0.0.1"],
        ["x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial",
         "-out", cert, "-days", "1", "-extfile", san],
    ):  # fmt: skip
        subprocess.run([openssl, *map(str, args)], check=True, capture_output=True, timeout=30)
    return ca, cert, key


def _make_password_file(directory: Path, user: str, password: str) -> Path:
    mosquitto_passwd = shutil.which("mosquitto_passwd")
    if mosquitto_passwd is None:
        pytest.skip("mosquitto_passwd is not installed (Debian package 'mosquitto')")
    path = directory / "passwd"
    subprocess.run(
        [mosquitto_passwd, "-b", "-c", str(path), user, password], check=True, timeout=30
    )
    return path


async def test_tls_and_password_authentication(
    mosquitto_factory: MosquittoFactory, tmp_path: Path
) -> None:
    ca, cert, key = _make_tls_files(tmp_path)
    passwords = _make_password_file(tmp_path, "dffd", "s3cret")
    broker = mosquitto_factory(
        listener_options=(
            "allow_anonymous false\n"
            f"password_file {passwords}\n"
            f"cafile {ca}\ncertfile {cert}\nkeyfile {key}\n"
        )
    )
    secure = settings(broker, tls=True, ca_file=ca, username="dffd", password="s3cret")
    async with Publisher(secure, TOPICS) as publisher:
        async with asyncio.timeout(MESSAGE_TIMEOUT_S):
            await publisher.wait_connected()
        tls = aiomqtt.TLSParameters(ca_certs=str(ca))
        async with aiomqtt.Client(
            broker.host, broker.port, username="dffd", password="s3cret", tls_params=tls
        ) as sub:
            await sub.subscribe(TOPICS.estimate)
            publisher.publish(estimate(42))
            async with asyncio.timeout(MESSAGE_TIMEOUT_S):
                message = await anext(aiter(sub.messages))
            assert json.loads(message.payload)["seq"] == 42  # type: ignore[arg-type]

    # a wrong password or no TLS: refused, retried with backoff, never a crash
    fast = {"connect_timeout_s": 0.5}  # plain MQTT on a TLS port only fails by timing out
    for bad in (
        settings(broker, tls=True, ca_file=ca, username="dffd", password="wrong", **fast),
        settings(broker, username="dffd", password="s3cret", **fast),
    ):
        async with Publisher(bad, TOPICS) as refused:
            await wait_until(lambda p=refused: p.stats().connect_failures >= 2)  # type: ignore[misc]
            assert not refused.connected
