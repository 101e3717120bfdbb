"""``dffd sim-camera``: serve the simulated VISCA camera on a pseudo-terminal, TCP or UDP.

Prints what it serves as the first line of stdout — the device path (the ``--link`` symlink, else
the pty slave), ``tcp://HOST:PORT`` for ``--listen tcp://…`` (raw VISCA) or
``visca-ip://HOST:PORT`` for ``--listen udp://…`` (VISCA over IP) — and, with ``--video
http://HOST:PORT``, the URL of its rendered frames as MJPEG over HTTP as the second line; serves
until SIGTERM or SIGINT, then exits 0.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from drivers.sim.models import SIM_MODELS, sim_model

# The device, the servers and asyncio are imported where they run: `dffd sim-camera --help` must
# parse its arguments without them (≤ 0.3 s, like every other subcommand's --help).
if TYPE_CHECKING:
    import contextlib

    from drivers.sim.device_types import DeviceConfig
    from drivers.sim.faults import Faults
    from drivers.sim.rig import SimCamera

logger = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the sim-camera options to ``parser``."""
    parser.add_argument(
        "--listen",
        metavar="URL",
        default="pty",
        help="pty (default), tcp://127.0.0.1:PORT (raw VISCA over TCP) or udp://127.0.0.1:PORT "
        "(VISCA over IP; prints visca-ip://…); port 0: any free one",
    )
    parser.add_argument(
        "--video",
        metavar="URL",
        default=None,
        help="also serve the rendered frames as MJPEG over HTTP on http://HOST:PORT (port 0: any "
        "free one); the video URL is printed as the second stdout line",
    )
    parser.add_argument(
        "--link",
        metavar="PATH",
        help="also create a symlink PATH to the pty (stable across port close/reopen faults)",
    )
    parser.add_argument(
        "--baud", type=int, default=9600, help="baud rate whose wire time is modelled (9600)"
    )
    parser.add_argument(
        "--no-pace",
        action="store_true",
        help="answer as fast as possible instead of pacing bytes at --baud (10 bits per byte)",
    )
    parser.add_argument(
        "--faults",
        metavar="SPEC",
        default="",
        help='seeded fault injection, e.g. "seed=3,drop=0.01,lose_completion=0.05" '
        "(keys: seed drop corrupt duplicate delay=P[:S] lose_completion garbage "
        "network_change_every power_cycle_every power_off close_port_every close_port_for "
        "direction)",
    )
    parser.add_argument(
        "--address",
        type=int,
        default=1,
        choices=range(1, 8),
        metavar="N",
        help="position of the camera in the daisy chain, 1–7 (its address after Address Set)",
    )
    parser.add_argument(
        "--model",
        default="evi-d100",
        choices=sorted(SIM_MODELS),
        help="camera model: its pan/tilt/focus/zoom limits, speed tables and VersionInq identity "
        "(default evi-d100)",
    )
    parser.add_argument(
        "--reply-from-a0",
        action="store_true",
        help="firmware quirk: send replies with header A0 instead of 90 (driver tests)",
    )


def run(args: argparse.Namespace) -> int:
    """Serve until SIGTERM/SIGINT; return the exit code."""
    import asyncio

    from drivers.sim.device_types import DeviceConfig
    from drivers.sim.faults import Faults, FaultSpecError

    try:
        faults = Faults(args.faults)
        config = DeviceConfig(
            address=args.address,
            baud=args.baud,
            pace=not args.no_pace,
            reply_from_a0=args.reply_from_a0,
            camera=sim_model(args.model),
        )
    except FaultSpecError as exc:
        print(f"dffd sim-camera: --faults: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as exc:
        print(f"dffd sim-camera: {exc}", file=sys.stderr)
        return EXIT_USAGE
    listen = args.listen.strip()
    tcp: tuple[str, int] | None = None
    scheme = "pty"
    if listen != "pty":
        parts = urlsplit(listen)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in ("tcp", "udp") or not parts.hostname or port is None:
            print(
                f"dffd sim-camera: --listen {listen!r}: use pty, tcp://HOST:PORT (raw VISCA) or "
                "udp://HOST:PORT (VISCA over IP); port 0: any free one",
                file=sys.stderr,
            )
            return EXIT_USAGE
        tcp, scheme = (parts.hostname, port), parts.scheme
    video: tuple[str, int] | None = None
    if args.video is not None:
        parts = urlsplit(args.video.strip())
        try:
            video_port = parts.port
        except ValueError:
            video_port = None
        if parts.scheme != "http" or not parts.hostname or video_port is None:
            print(
                f"dffd sim-camera: --video {args.video!r}: use http://HOST:PORT (port 0: any "
                "free one)",
                file=sys.stderr,
            )
            return EXIT_USAGE
        video = (parts.hostname, video_port)
    try:
        if tcp is not None:
            return asyncio.run(_serve_net(scheme, config, faults, *tcp, video=video))
        return asyncio.run(_serve(config, faults, args.link, video=video))
    except OSError as exc:
        print(
            f"dffd sim-camera: cannot serve the pty ({exc}); check --link is a writable path",
            file=sys.stderr,
        )
        return EXIT_FAILURE


async def _serve(
    config: DeviceConfig, faults: Faults, link: str | None, *, video: tuple[str, int] | None
) -> int:
    import asyncio
    import contextlib
    import signal

    from drivers.sim.server import SimCameraServer

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    async with contextlib.AsyncExitStack() as stack:
        rig = _rig(config) if video is not None else None
        state = rig.state if rig is not None else None
        server = SimCameraServer(config, faults=faults, link_path=link, state=state)
        await stack.enter_async_context(server)
        sys.stdout.write(f"{server.path}\n")
        await _serve_video(stack, rig, video)
        sys.stdout.flush()
        logger.info("sim camera %s on %s, faults: %s", config, server.path, faults.spec)
        await stop.wait()
    return EXIT_OK


def _rig(config: DeviceConfig) -> SimCamera:
    """The reference simulated camera (renderer and world) driven by the VISCA device."""
    # Imported here: the renderer pulls in numpy and OpenCV, which `--help` must not load.
    from drivers.sim.config import load_sim_camera_config
    from drivers.sim.resources import reference_camera_file
    from drivers.sim.rig import build_sim_camera

    return build_sim_camera(load_sim_camera_config(reference_camera_file()), device=config)


async def _serve_video(
    stack: contextlib.AsyncExitStack, rig: SimCamera | None, video: tuple[str, int] | None
) -> None:
    if rig is None or video is None:
        return
    from drivers.sim.video_server import SimVideoServer

    server = SimVideoServer(rig.source, host=video[0], port=video[1])
    await stack.enter_async_context(server)
    sys.stdout.write(f"{server.url}\n")


async def _serve_net(
    scheme: str,
    config: DeviceConfig,
    faults: Faults,
    host: str,
    port: int,
    *,
    video: tuple[str, int] | None,
) -> int:
    import asyncio
    import contextlib
    import signal

    from drivers.sim.ip_server import SimUdpServer
    from drivers.sim.net_server import SimTcpServer

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    server_cls = SimUdpServer if scheme == "udp" else SimTcpServer
    async with contextlib.AsyncExitStack() as stack:
        rig = _rig(config) if video is not None else None
        state = rig.state if rig is not None else None
        server = server_cls(config, host=host, port=port, faults=faults, state=state)
        await stack.enter_async_context(server)
        sys.stdout.write(f"{server.url}\n")
        await _serve_video(stack, rig, video)
        sys.stdout.flush()
        logger.info("sim camera %s on %s, faults: %s", config, server.url, faults.spec)
        await stop.wait()
    return EXIT_OK
