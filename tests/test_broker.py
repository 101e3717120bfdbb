"""Embedded amqtt broker: a full Publisher round trip, and a clear error when the port is taken."""

from __future__ import annotations

import asyncio
import json
import socket
import time

import aiomqtt
import jsonschema
import pytest

from dffd.daemon.broker import BrokerStartError, EmbeddedBroker
from dffd.mqtt import schemas
from dffd.mqtt.models import DepthByEstimator, Estimate
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics

from .conftest import free_port

# Loopback round trips take milliseconds; 5 s absorbs a loaded CI machine.
MESSAGE_TIMEOUT_S = 5.0
TOPICS = Topics("dffd", "sim")


def _estimate(seq: int) -> Estimate:
    return Estimate(
        seq=seq,
        t=time.time(),
        t_mono=time.monotonic(),
        state="tracking",
        depth_m=DepthByEstimator(measured=1.9, cf1=None, cf2=2.0, lpv=2.0, kf=2.0),
        best="lpv",
        z_m=2.0,
        sigma_m=0.02,
        size_m=0.036,
        r_px=40.0,
        position_m=(0.0, 0.0, 2.0),
        pan_deg=0.0,
        tilt_deg=0.0,
    )


async def _next_json(client: aiomqtt.Client, topic: str) -> dict[str, object]:
    async with asyncio.timeout(MESSAGE_TIMEOUT_S):
        async for message in client.messages:
            if message.topic.matches(topic):
                assert isinstance(message.payload, bytes)
                data: dict[str, object] = json.loads(message.payload)
                return data
    raise AssertionError("unreachable: the iterator only ends by raising")


async def test_round_trip_through_embedded_broker() -> None:
    port = free_port()
    async with EmbeddedBroker(port) as broker:
        assert broker.url == f"mqtt://127.0.0.1:{port}"
        settings = PublisherSettings("127.0.0.1", port, reconnect_min_s=0.05, reconnect_max_s=0.2)
        async with Publisher(settings, TOPICS) as publisher:
            async with asyncio.timeout(MESSAGE_TIMEOUT_S):
                await publisher.wait_connected()
            async with aiomqtt.Client("127.0.0.1", port) as sub:
                await sub.subscribe(f"{TOPICS.base}/#", qos=1)
                status = await _next_json(sub, TOPICS.status)  # retained online
                assert status["availability"] == "online"
                publisher.publish(_estimate(7))
                got = await _next_json(sub, TOPICS.estimate)
                assert got["seq"] == 7
                jsonschema.validate(got, schemas.load("estimate"))
                await sub.publish(TOPICS.cmd, b'{"cmd": "ping", "id": 1}', qos=1)
                reply = await _next_json(sub, TOPICS.cmd_reply)
                assert reply["ok"] is True
                assert reply["id"] == 1
                await publisher.stop()
                offline = await _next_json(sub, TOPICS.status)
                assert offline["availability"] == "offline"
    # stopped: the port is free again
    with socket.create_server(("127.0.0.1", port)):
        pass


async def test_taken_port_is_a_clear_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as squatter:
        port = squatter.getsockname()[1]
        with pytest.raises(BrokerStartError, match=r"already in use.*embedded_port"):
            async with EmbeddedBroker(port):
                pass


async def test_stop_is_idempotent_and_safe_before_start() -> None:
    broker = EmbeddedBroker(free_port())
    await broker.stop()
    await broker.start()
    await broker.stop()
    await broker.stop()
