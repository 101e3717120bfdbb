"""Round-trip timing of the simulated camera over its pty, with a bare pyserial client.

``python -m drivers.sim.bench [N]`` prints the median and p95 inquiry round trip (VersionInq,
5 bytes out, 10 back) with pacing off and with 9600-baud pacing, the latter also as a ratio to
the wire time of the 15 bytes. This times the simulator, not the driver: the link's own
benchmark adds its overhead on top.
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import time

import serial

from drivers.sim.device_types import FIELD_PERIOD_S, DeviceConfig
from drivers.sim.server import SimCameraServer
from drivers.visca import codec, codec_requests

DEFAULT_ROUNDS = 200
REPLY_TIMEOUT_S = 1.0  # a reply is due within ~1 field plus wire time; this only stops a hang
BAUD = 9600


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one line per configuration."""
    args = sys.argv[1:] if argv is None else argv
    rounds = int(args[0]) if args else DEFAULT_ROUNDS
    request = codec.encode_request(codec_requests.VersionInquiry(), 1)
    wire_s = (len(request) + 10) * 10 / BAUD
    print(f"field {FIELD_PERIOD_S * 1e3:.2f} ms, wire time of the exchange {wire_s * 1e3:.2f} ms")
    for pace in (False, True):
        times = asyncio.run(_measure(DeviceConfig(pace=pace, baud=BAUD), request, rounds))
        median = statistics.median(times)
        p95 = statistics.quantiles(times, n=20)[-1]
        label = "9600" if pace else "off "
        line = f"pace={label}: median {median * 1e3:.2f} ms, p95 {p95 * 1e3:.2f} ms"
        if pace:
            line += f", median/wire = {median / wire_s:.2f}"
        print(line)
    return 0


async def _measure(config: DeviceConfig, request: bytes, rounds: int) -> list[float]:
    async with SimCameraServer(config) as server:
        return await asyncio.to_thread(_client, server.path, request, rounds)


def _client(path: str, request: bytes, rounds: int) -> list[float]:
    times: list[float] = []
    with serial.serial_for_url(path, baudrate=BAUD, timeout=REPLY_TIMEOUT_S) as port:
        port.read_until(b"\xff")  # the power-up Network Change (or a timeout if flushed)
        for _ in range(rounds):
            t0 = time.perf_counter()
            port.write(request)
            reply = port.read_until(b"\xff")
            times.append(time.perf_counter() - t0)
            if not reply.startswith(b"\x90\x50"):
                raise RuntimeError(f"unexpected reply {reply.hex(' ')}")
    return times


if __name__ == "__main__":
    sys.exit(main())
