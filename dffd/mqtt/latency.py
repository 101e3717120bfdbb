"""Measure publish → subscriber latency of Estimate messages through a broker.

``python -m dffd.mqtt.latency [--url embedded|mqtt://host:port] [--rate 30] [--seconds 5]``
publishes Estimates through :class:`~dffd.mqtt.publisher.Publisher` at ``--rate`` Hz, receives
them with a plain subscriber in the same process and prints p50/p99/max of (receive time −
``t_mono``), plus the CPU cost of building and serialising one Estimate. Publisher and
subscriber share the monotonic clock, so no clock sync is involved. This is the MQTT share of
docs/design.md §10's exposure → subscriber budget (p50 ≤ 10 ms, p99 ≤ 30 ms).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import sys
import time
from collections.abc import Sequence

import aiomqtt

from dffd.daemon.broker import EmbeddedBroker
from dffd.mqtt.models import DepthByEstimator, Estimate
from dffd.mqtt.publisher import Publisher
from dffd.mqtt.publisher_types import PublisherSettings
from dffd.mqtt.topics import Topics

# Connecting to a local broker takes milliseconds; 10 s covers a remote one.
CONNECT_TIMEOUT_S = 10.0
# After the last publish, wait this long for stragglers (≫ any plausible p99).
DRAIN_TIMEOUT_S = 2.0
_EMBEDDED_PORT_PROBE = ("127.0.0.1", 0)


def make_estimate(seq: int, t_mono: float) -> Estimate:
    """A fully populated Estimate (the size of a real one)."""
    return Estimate(
        seq=seq,
        t=time.time(),
        t_mono=t_mono,
        state="tracking",
        depth_m=DepthByEstimator(measured=2.01, cf1=None, cf2=2.0, lpv=2.0, kf=2.0),
        best="lpv",
        z_m=2.0,
        sigma_m=0.03,
        beta_m_s=0.001,
        size_m=0.0358,
        r_px=41.5,
        rho_per_s=-0.02,
        position_m=(0.1, -0.2, 2.0),
        velocity_m_s=(0.0, 0.0, -0.1),
        pan_deg=1.5,
        tilt_deg=-0.5,
        focus_counts=0x4000,
    )


def serialisation_cost_us(n: int = 5000) -> float:
    """Mean µs to build (validate) and serialise one Estimate."""
    start = time.perf_counter()
    for seq in range(n):
        make_estimate(seq, 0.0).to_json()
    return (time.perf_counter() - start) / n * 1e6


async def measure(host: str, port: int, rate_hz: float, seconds: float) -> list[float]:
    """Latencies in seconds of ``rate_hz × seconds`` Estimates through ``host:port``."""
    topics = Topics("dffd", "latency")
    latencies: list[float] = []
    count = max(1, round(rate_hz * seconds))
    done = asyncio.Event()
    nodelay = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)
    async with (
        aiomqtt.Client(host, port, socket_options=nodelay) as sub,
        Publisher(PublisherSettings(host, port, queue_max_messages=count), topics) as pub,
    ):
        await sub.subscribe(topics.estimate)
        async with asyncio.timeout(CONNECT_TIMEOUT_S):
            await pub.wait_connected()

        async def receive() -> None:
            async for message in sub.messages:
                assert isinstance(message.payload, bytes)
                sent = json.loads(message.payload)["t_mono"]
                latencies.append(time.monotonic() - sent)
                if len(latencies) >= count:
                    done.set()
                    return

        receiver = asyncio.create_task(receive())
        period = 1.0 / rate_hz
        start = time.monotonic()
        for seq in range(count):
            await asyncio.sleep(max(0.0, start + seq * period - time.monotonic()))
            pub.publish(make_estimate(seq, time.monotonic()))
        try:
            async with asyncio.timeout(DRAIN_TIMEOUT_S):
                await done.wait()
        except TimeoutError:
            pass
        receiver.cancel()
        await asyncio.gather(receiver, return_exceptions=True)
    return latencies


async def _main(url: str, rate_hz: float, seconds: float) -> int:
    if url == "embedded":
        with socket.socket() as probe:
            probe.bind(_EMBEDDED_PORT_PROBE)
            port = int(probe.getsockname()[1])
        async with EmbeddedBroker(port):
            latencies = await measure("127.0.0.1", port, rate_hz, seconds)
    else:
        host, _, port_text = url.removeprefix("mqtt://").partition(":")
        latencies = await measure(host, int(port_text or 1883), rate_hz, seconds)
    expected = max(1, round(rate_hz * seconds))
    if not latencies:
        print("no message arrived", file=sys.stderr)
        return 1
    ms = sorted(x * 1e3 for x in latencies)
    p99 = ms[min(len(ms) - 1, int(0.99 * len(ms)))]
    print(
        f"{url}: {len(ms)}/{expected} received at {rate_hz:g} Hz; latency ms "
        f"p50 {statistics.median(ms):.2f} p99 {p99:.2f} max {ms[-1]:.2f}; "
        f"build+serialise {serialisation_cost_us():.1f} µs/estimate"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(prog="python -m dffd.mqtt.latency", description=__doc__)
    parser.add_argument("--url", default="embedded", help="embedded (default) or mqtt://host:port")
    parser.add_argument("--rate", type=float, default=30.0, help="messages per second")
    parser.add_argument("--seconds", type=float, default=5.0, help="duration")
    args = parser.parse_args(argv)
    return asyncio.run(_main(args.url, args.rate, args.seconds))


if __name__ == "__main__":
    sys.exit(main())
