"""VISCA driver round-trip benchmark against the simulated camera over a real pty (issue 2).

    python -m hil.bench_visca [--n N] [--out FILE]

Times ``ViscaLink.command`` for Pan-tiltDrive Stop (9 bytes out; ACK + Completion, 6 bytes
back: a full command round trip) and ``ViscaLink.inquire`` for FocusPosInq (5 out, 7 back):

* ``unpaced``: the simulator answers at once (no wire time, no video-field wait): what is left
  is the driver's overhead plus the pty and the simulator's event loop.
* ``paced_9600``: every byte takes 10 bit times at 9600 baud in the simulator (video-field wait
  still off): the median round trip as a ratio to the wire time of the bytes exchanged.
* ``paced_9600_field``: as above with the camera's one-message-per-field (1/60 s) timing, i.e.
  what a real EVI-D100 at 9600 baud would give (informational).

Prints the figures; ``--out`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Any

from drivers.sim.device_types import BITS_PER_BYTE, FIELD_PERIOD_S, DeviceConfig
from drivers.sim.server import SimCameraServer
from drivers.visca import codec_requests
from drivers.visca.camera import Camera
from drivers.visca.link import ViscaLink

BAUD = 9600
# "No field wait": the simulator still quantises to fields; a microsecond field makes that nil.
NO_FIELD_S = 1e-6
DEFAULT_N = 200
WARMUP = 10


async def measure(config: DeviceConfig, n: int) -> dict[str, Any]:
    """Median/p90 round trips (ms) of a command and an inquiry against ``config``."""
    async with SimCameraServer(config) as server, ViscaLink(server.path, BAUD) as link:
        await Camera(link).initialize()  # retries if the power-up Network Change races it
        out: dict[str, Any] = {"pace": config.pace, "field_period_s": config.field_period_s}
        stop = codec_requests.PanTiltDrive.stop()
        inquiry = codec_requests.FocusPositionInquiry()
        cases: dict[str, Callable[[], Awaitable[object]]] = {
            "command": lambda: link.command(1, stop),
            "inquiry": lambda: link.inquire(1, inquiry),
        }
        for name, call in cases.items():
            for _ in range(WARMUP):
                await call()
            before = link.health()
            samples: list[float] = []
            for _ in range(n):
                start = time.perf_counter()
                await call()
                samples.append(time.perf_counter() - start)
            after = link.health()
            exchanged = (after.bytes_out - before.bytes_out + after.bytes_in - before.bytes_in) / n
            wire_s = exchanged * BITS_PER_BYTE / BAUD
            median = statistics.median(samples)
            out[name] = {
                "n": n,
                "median_ms": median * 1e3,
                "p90_ms": statistics.quantiles(samples, n=10)[-1] * 1e3,
                "min_ms": min(samples) * 1e3,
                "bytes_exchanged": exchanged,
                "wire_ms_at_9600": wire_s * 1e3,
                "ratio_to_wire": median / wire_s,
            }
        return out


async def run(n: int = DEFAULT_N) -> dict[str, Any]:
    """All three configurations."""
    return {
        "schema": 1,
        "benchmark": "visca_round_trip",
        "unpaced": await measure(DeviceConfig(pace=False, field_period_s=NO_FIELD_S), n),
        "paced_9600": await measure(
            DeviceConfig(pace=True, baud=BAUD, field_period_s=NO_FIELD_S), n
        ),
        "paced_9600_field": await measure(
            DeviceConfig(pace=True, baud=BAUD, field_period_s=FIELD_PERIOD_S), max(20, n // 4)
        ),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--n", type=int, default=DEFAULT_N, help="round trips per case")
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    args = parser.parse_args(argv)
    result = asyncio.run(run(args.n))
    for mode in ("unpaced", "paced_9600", "paced_9600_field"):
        for case in ("command", "inquiry"):
            r = result[mode][case]
            print(
                f"{mode:17s} {case:8s} median {r['median_ms']:7.3f} ms  p90 {r['p90_ms']:7.3f} ms"
                f"  ({r['bytes_exchanged']:.0f} B, wire {r['wire_ms_at_9600']:.2f} ms at 9600,"
                f" ratio {r['ratio_to_wire']:.3f})"
            )
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
