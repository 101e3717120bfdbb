"""The service's publish path at the frame rate: core output → MQTT subscriber (issue 15).

Against a real mosquitto on loopback, at ``--rate`` messages/s (30: an estimate on every frame),
two latencies are measured from the same subscriber with one clock (``time.monotonic``):

* **floor** — a bare ``aiomqtt`` client publishing pre-serialised bytes of an estimate's size:
  what the broker and the loopback cost, nothing of dffd's;
* **path** — the daemon's own hand-off: a stand-in estimator thread hands a core
  :class:`~dffd.core.pipeline.Estimate` (with a 3D track) to the event loop with
  ``call_soon_threadsafe`` at the moment its frame is done, the loop converts it with
  :class:`~dffd.daemon.payloads.Payloads` and queues it on the daemon's
  :class:`~dffd.mqtt.publisher.Publisher`, which sends it.

The difference is what dffd adds between "frame processed" and "message at a subscriber"; the
estimator thread's per-frame CPU and the capture are not in it. Also reported: the publishing
event loop thread's CPU per message (payload build, serialisation, send) from the thread's CPU
clock; the subscriber runs in a thread and event loop of its own.

    python -m hil.bench_publish [--messages 600] [--rate 30] [--out bench_publish.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# Subscriber connect and the first message: a loopback broker answers in milliseconds.
CONNECT_TIMEOUT_S = 10.0
# Messages still in flight when the sender stops: they arrive within milliseconds.
DRAIN_TIMEOUT_S = 5.0
# Messages before timing starts (connection warm-up, first allocation of buffers).
WARMUP_MESSAGES = 30


def main(argv: Sequence[str] | None = None) -> int:
    """Run both measurements, print them, write JSON to ``--out``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--messages", type=int, default=600, help="timed messages per mode")
    parser.add_argument("--rate", type=float, default=30.0, help="messages per second")
    parser.add_argument("--out", type=Path, default=None, help="JSON result file")
    args = parser.parse_args(argv)
    if args.messages < 1 or args.rate <= 0:
        parser.error("--messages must be >= 1 and --rate > 0")
    result = asyncio.run(measure(args.messages, args.rate))
    for mode in ("floor", "path"):
        r = result[mode]
        print(
            f"{mode:<6s} n {r['n']:4d}  p50 {r['p50_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms  "
            f"max {r['max_ms']:.3f} ms  loop CPU {r['loop_cpu_ms_per_message']:.3f} ms/message"
        )
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")
    return 0


async def measure(messages: int, rate: float) -> dict[str, Any]:
    """Floor and path latency (ms) at ``rate`` against a fresh mosquitto."""
    from hil.realtime import _free_port as free_port
    from hil.realtime import _start_mosquitto as start_mosquitto
    from hil.realtime import _stop as stop_process

    with tempfile.TemporaryDirectory(prefix="hil-bench-publish-") as tmp:
        port = free_port()
        broker = start_mosquitto(Path(tmp), port)
        if broker is None:
            raise SystemExit("hil.bench_publish needs mosquitto (apt-get install mosquitto)")
        try:
            floor = await _floor(port, messages, rate)
            path = await _path(port, messages, rate)
        finally:
            stop_process(broker)
    return {
        "what": "core output handed over -> MQTT subscriber (mosquitto on loopback), ms",
        "rate_hz": rate,
        "messages": messages,
        "floor": floor,
        "path": path,
        "added_p50_ms": path["p50_ms"] - floor["p50_ms"],
        "added_p99_ms": path["p99_ms"] - floor["p99_ms"],
    }


async def _floor(port: int, messages: int, rate: float) -> dict[str, Any]:
    """Bare aiomqtt publishes of estimate-sized bytes carrying their send time."""
    import aiomqtt

    size = len(_sample_payload_json())
    total = messages + WARMUP_MESSAGES
    async with _Subscriber(port, "bench/floor") as sub, aiomqtt.Client("127.0.0.1", port) as pub:
        # The subscriber reads while the messages arrive (its receipt time is the figure).
        collecting = asyncio.create_task(sub.collect(total))
        c0 = time.thread_time()
        start = time.monotonic()
        for i in range(total):
            await asyncio.sleep(max(0.0, start + i / rate - time.monotonic()))
            head = f'{{"i":{i},"t_mono":{time.monotonic()!r},"pad":"'.encode()
            await pub.publish("bench/floor", head + b"x" * max(0, size - len(head) - 2) + b'"}')
        lat = await collecting
        cpu = time.thread_time() - c0
    return _stats(lat[WARMUP_MESSAGES:]) | {
        "loop_cpu_ms_per_message": 1e3 * cpu / total,
        "payload_bytes": size,
    }


async def _path(port: int, messages: int, rate: float) -> dict[str, Any]:
    """The daemon's hand-off, payload conversion and Publisher, fed from a thread."""
    from dffd.daemon.payloads import Payloads
    from dffd.mqtt.publisher import Publisher
    from dffd.mqtt.publisher_types import PublisherSettings
    from dffd.mqtt.topics import Topics

    topics = Topics(prefix="bench", camera="path")
    publisher = Publisher(PublisherSettings(host="127.0.0.1", port=port), topics)
    payloads = Payloads("lpv")
    loop = asyncio.get_running_loop()
    total = messages + WARMUP_MESSAGES

    def on_result(item: tuple[Any, Any]) -> None:  # the daemon's results loop, minus the rest
        payload = payloads.estimate(*item)
        if payload is not None:
            publisher.publish(payload)

    async with _Subscriber(port, topics.estimate) as sub, publisher:
        async with asyncio.timeout(CONNECT_TIMEOUT_S):
            await publisher.wait_connected()
        done = threading.Event()
        feeder = threading.Thread(
            target=_feed, args=(loop, on_result, total, rate, done), name="bench-estimator"
        )
        c0 = time.thread_time()
        feeder.start()
        try:
            lat = await sub.collect(total)
        finally:
            done.set()
            feeder.join(DRAIN_TIMEOUT_S)
        cpu = time.thread_time() - c0
    return _stats(lat[WARMUP_MESSAGES:]) | {
        "loop_cpu_ms_per_message": 1e3 * cpu / total,
        "payload_bytes": len(_sample_payload_json()),
    }


def _feed(
    loop: asyncio.AbstractEventLoop,
    deliver: Callable[[tuple[Any, Any]], None],
    total: int,
    rate: float,
    done: threading.Event,
) -> None:
    """The stand-in estimator thread: one finished frame every 1/rate s."""
    period = 1.0 / rate
    start = time.monotonic()
    for i in range(total):
        if done.wait(max(0.0, start + i * period - time.monotonic())):
            return
        est, track = sample_outputs(i, time.monotonic())
        loop.call_soon_threadsafe(deliver, (est, track))


def sample_outputs(index: int, t: float) -> tuple[Any, Any]:
    """A core estimate with a 3D track as the service produces them while tracking."""
    from dffd.core.pipeline import Estimate
    from dffd.core.tracking3d_types import Track3DEstimate

    z = 4.0 + 0.001 * index
    est = Estimate(
        frame_index=index, t=t, state="tracking",
        depth_m={"measured": z + 0.01, "cf1": None, "cf2": z, "lpv": z - 0.002, "kf": z + 0.001},
        measured_t=t - 0.2, best="lpv", z_m=z - 0.002, sigma_m=0.012, beta_m_s=0.003,
        lpv_b_m_s=0.001, size_m=0.03576, r_px=71.3, rho=0.02, centroid_px=(321.5, 240.25),
        position_m=(0.1, -0.05, z), velocity_m_s=(0.01, 0.0, 0.2),
        position_world_m=(0.1, -0.05, z), velocity_world_m_s=(0.01, 0.0, 0.2),
        pan_deg=1.25, tilt_deg=-0.5, focus_counts=4123, inlier_fraction=0.97,
    )  # fmt: skip
    track = Track3DEstimate(
        t=t,
        position_m=(0.1, -0.05, z),
        velocity_m_s=(0.01, 0.0, 0.2),
        acceleration_m_s2=(0.0, 0.0, 0.01),
        angular_speed_rad_s=0.05,
        position_sigma_m=(0.004, 0.004, 0.012),
        model_probabilities={"cv": 0.7, "ca": 0.2, "ct": 0.1},
    )
    return est, track


def _sample_payload_json() -> bytes:
    from dffd.daemon.payloads import Payloads

    payload = Payloads("lpv").estimate(*sample_outputs(1, 1.0))
    assert payload is not None
    return payload.to_json()


class _Subscriber:
    """Subscribes to one topic in its own thread and event loop (so the publishing loop's CPU
    clock counts only the publisher); ``collect(n)`` returns n latencies (s) from ``t_mono``."""

    def __init__(self, port: int, topic: str) -> None:
        self.port = port
        self.topic = topic
        self._want = 0
        self._ready = threading.Event()
        self._start = threading.Event()
        self._done = threading.Event()
        self._latencies: list[float] = []
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="bench-subscriber", daemon=True)

    async def __aenter__(self) -> _Subscriber:
        self._thread.start()
        ready = await asyncio.to_thread(self._ready.wait, CONNECT_TIMEOUT_S)
        if not ready or self._error is not None:
            raise RuntimeError(f"subscriber did not connect: {self._error!r}")
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._done.set()
        self._start.set()
        await asyncio.to_thread(self._thread.join, DRAIN_TIMEOUT_S)

    async def collect(self, n: int) -> list[float]:
        """Wait for ``n`` messages (sent by the caller meanwhile); their latencies."""
        self._want = n
        self._start.set()
        # The run itself lasts n/rate s; the bound covers it plus a loaded machine.
        finished = await asyncio.to_thread(self._done.wait, CONNECT_TIMEOUT_S + DRAIN_TIMEOUT_S + n)
        if not finished or self._error is not None:
            raise RuntimeError(f"subscriber got {len(self._latencies)} of {n}: {self._error!r}")
        return list(self._latencies)

    def _main(self) -> None:
        try:
            asyncio.run(self._receive())
        except BaseException as exc:  # noqa: BLE001 - reported to the caller
            self._error = exc
            self._ready.set()
        finally:
            self._done.set()

    async def _receive(self) -> None:
        import aiomqtt

        async with aiomqtt.Client("127.0.0.1", self.port) as client:
            await client.subscribe(self.topic)
            self._ready.set()
            await asyncio.to_thread(self._start.wait, CONNECT_TIMEOUT_S + DRAIN_TIMEOUT_S)
            if self._done.is_set():
                return
            async for message in client.messages:
                now = time.monotonic()
                assert isinstance(message.payload, bytes)
                self._latencies.append(now - float(json.loads(message.payload)["t_mono"]))
                if len(self._latencies) >= self._want:
                    return


def _stats(latencies: Sequence[float]) -> dict[str, Any]:
    a = 1e3 * np.asarray(latencies, dtype=np.float64)
    if a.size == 0:
        return {"n": 0, "p50_ms": math.nan, "p99_ms": math.nan, "max_ms": math.nan}
    return {
        "n": int(a.size),
        "p50_ms": float(np.percentile(a, 50)),
        "p90_ms": float(np.percentile(a, 90)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
        "mean_ms": float(a.mean()),
    }


if __name__ == "__main__":
    sys.exit(main())
