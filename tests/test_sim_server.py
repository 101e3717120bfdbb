"""The simulated camera over a real pseudo-terminal, opened with pyserial like hardware."""

from __future__ import annotations

import asyncio
import os
import select
import signal
import subprocess
import sys
import time
import tty
from pathlib import Path

import pytest
import serial

from drivers.sim.device_types import DeviceConfig
from drivers.sim.server import SimCameraServer
from drivers.visca import codec, codec_framing, codec_replies, codec_requests

# Replies come within ~1 field (17 ms); this only bounds a test on a loaded 2-core CI machine.
SERIAL_TIMEOUT_S = 2.0
# A read that must stay empty: several fields, so a wrong reply would have arrived by then.
SILENCE_S = 0.2
# Start-up of `dffd sim-camera` as a subprocess (interpreter + imports) on a slow machine.
CLI_START_TIMEOUT_S = 20.0
# A raw controller's read of one reply, and the wait for the camera to finish a move.
RAW_READ_TIMEOUT_S = 2.0
WAIT_S = 5.0

VERSION_INQ = codec.encode_request(codec_requests.VersionInquiry(), 1)
VERSION_REPLY = bytes.fromhex("90 50 00 01 04 0D 02 00 02 FF")


def open_port(path: str, timeout: float = SERIAL_TIMEOUT_S) -> serial.Serial:
    return serial.serial_for_url(path, baudrate=9600, timeout=timeout)


NETWORK_CHANGE = b"\x90\x38\xff"


def read_reply(port: serial.Serial) -> bytes:
    """The next packet that is not the power-up Network Change (b"" on timeout)."""
    while (packet := bytes(port.read_until(b"\xff"))) == NETWORK_CHANGE:
        pass
    return packet


def ask(path: str, request: bytes, timeout: float = SERIAL_TIMEOUT_S) -> bytes:
    """Open ``path``, write ``request``, return the first reply packet (b"" on timeout)."""
    with open_port(path, timeout) as port:
        port.write(request)
        return read_reply(port)


async def test_inquiry_round_trip_over_pty() -> None:
    async with SimCameraServer() as server:
        assert server.path.startswith("/dev/pts/")
        assert await asyncio.to_thread(ask, server.path, VERSION_INQ) == VERSION_REPLY
        assert server.device.stats.packets_in == 1


async def test_command_moves_the_state_and_completes() -> None:
    async with SimCameraServer(DeviceConfig(autofocus_at_power_up=False)) as server:

        def focus() -> bytes:
            with open_port(server.path) as port:
                port.write(codec.encode_request(codec_requests.FocusDirect(0x1800), 1))
                return read_reply(port) + read_reply(port)

        assert await asyncio.to_thread(focus) == bytes.fromhex("90 41 FF 90 51 FF")
        assert server.state.snapshot().focus_counts == 0x1800


async def test_paced_round_trip_takes_at_least_the_wire_time() -> None:
    async with SimCameraServer(DeviceConfig(pace=True, baud=9600)) as server:

        def timed() -> float:
            with open_port(server.path) as port:
                t0 = time.perf_counter()
                port.write(VERSION_INQ)
                assert read_reply(port) == VERSION_REPLY
                return time.perf_counter() - t0

        elapsed = await asyncio.to_thread(timed)
        wire_s = (len(VERSION_INQ) + len(VERSION_REPLY)) * 10 / 9600
        assert elapsed >= wire_s


async def test_one_shot_faults_over_pty() -> None:
    async with SimCameraServer() as server, asyncio.timeout(10):
        port = await asyncio.to_thread(open_port, server.path)
        try:
            server.faults.inject_network_change()
            assert await asyncio.to_thread(port.read_until, b"\xff") == b"\x90\x38\xff"
            server.faults.set_silent(True)
            port.timeout = SILENCE_S
            await asyncio.to_thread(port.write, VERSION_INQ)
            assert await asyncio.to_thread(port.read, 1) == b""
            server.faults.set_silent(False)
            server.faults.power_cycle(off_s=0.05)
            port.timeout = SERIAL_TIMEOUT_S
            assert await asyncio.to_thread(port.read_until, b"\xff") == b"\x90\x38\xff"
            await asyncio.to_thread(port.write, VERSION_INQ)
            assert await asyncio.to_thread(port.read_until, b"\xff") == VERSION_REPLY
        finally:
            port.close()


async def test_close_and_reopen_port_with_stable_symlink(tmp_path: Path) -> None:
    link = tmp_path / "visca-cam"
    async with SimCameraServer(link_path=link) as server:
        assert server.path == str(link)
        first_slave = os.readlink(link)
        assert first_slave == server.slave_name
        port = await asyncio.to_thread(open_port, server.path)
        try:
            server.close_port()
            assert not link.exists()
            assert not server.port_open
            with pytest.raises(serial.SerialException):
                # The pty is gone: reading fails (EIO) instead of hanging.
                await asyncio.to_thread(port.read, 1)
            with pytest.raises(serial.SerialException):
                await asyncio.to_thread(open_port, str(link))
        finally:
            port.close()
        server.reopen_port()
        assert server.port_open
        assert os.readlink(link) == server.slave_name
        assert await asyncio.to_thread(ask, str(link), VERSION_INQ) == VERSION_REPLY
    assert not link.exists()


async def test_periodic_port_close_from_fault_spec(tmp_path: Path) -> None:
    link = tmp_path / "cam"
    spec = "close_port_every=0.2,close_port_for=0.02"  # open 0.2 s: time to check the link
    async with SimCameraServer(link_path=link, faults=spec) as server, asyncio.timeout(10):
        await server.wait_port_generation(3)
        assert os.readlink(link) == server.slave_name
    assert not link.exists()


def test_cli_prints_path_first_answers_and_exits_0_on_sigterm(tmp_path: Path) -> None:
    link = tmp_path / "cam"
    proc = subprocess.Popen(
        [sys.executable, "-m", "dffd", "sim-camera", "--link", str(link), "--faults", "seed=1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first = _readline_with_timeout(proc, CLI_START_TIMEOUT_S)
        assert first == f"{link}\n"
        assert ask(first.strip(), VERSION_INQ) == VERSION_REPLY
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=CLI_START_TIMEOUT_S) == 0
        assert not link.exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        assert proc.stdout is not None
        assert proc.stderr is not None
        proc.stdout.close()
        proc.stderr.close()


def test_cli_rejects_a_bad_fault_spec_naming_the_key() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "dffd", "sim-camera", "--faults", "seed=1,dorp=0.5"],
        capture_output=True,
        text=True,
        timeout=CLI_START_TIMEOUT_S,
        check=False,
    )
    assert result.returncode == 2
    assert "'dorp'" in result.stderr
    assert result.stdout == ""


def _readline_with_timeout(proc: subprocess.Popen[str], timeout: float) -> str:
    assert proc.stdout is not None
    import selectors

    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            raise AssertionError(f"sim-camera printed nothing within {timeout} s")
    return proc.stdout.readline()


# ---- a controller that attaches late reads only its own replies ------------------------------


def _read_packets(fd: int, count: int) -> list[bytes]:
    """Read ``count`` complete packets from a blocking fd (bounded by a select timeout)."""
    reassembler = codec_framing.Reassembler()
    found: list[bytes] = []
    while len(found) < count:
        ready, _, _ = select.select([fd], [], [], RAW_READ_TIMEOUT_S)
        if not ready:
            break
        found += reassembler.feed(os.read(fd, 64))
    return found


async def _exchange_raw(path: str, request: codec_requests.Request, replies: int) -> list[bytes]:
    """Open the pty like libvisca does (os.open, no flush), write, read ``replies`` packets."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        os.write(fd, codec.encode_request(request, 1))
        return await asyncio.to_thread(_read_packets, fd, replies)
    finally:
        os.close(fd)


async def test_a_controller_opening_the_pty_late_reads_only_replies_to_its_own_commands() -> None:
    config = DeviceConfig(autofocus_at_power_up=False, focus_speed_counts_s=0x7400 / 0.1)
    async with SimCameraServer(config, stale_output_s=0.05) as server:
        # The power-up Network Change went to nobody: it is gone once it has waited 50 ms.
        await asyncio.wait_for(_discarded(server, 3), WAIT_S)
        first = await _exchange_raw(server.path, codec_requests.VersionInquiry(), 1)
        assert first == [codec.encode_reply(codec_replies.InquiryReply(
            codec_replies.Version(0x0001, 0x040D, 0x0200, 2).to_data()), 1)]  # fmt: skip
        # A controller that sends a move and leaves: its Completion comes after it has gone.
        fd = os.open(server.path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        os.write(fd, codec.encode_request(codec_requests.FocusDirect(0x8000), 1))
        os.close(fd)
        await asyncio.wait_for(_discarded(server, 3 + 6), WAIT_S)
        second = await _exchange_raw(server.path, codec_requests.PowerInquiry(), 1)
        assert second == [bytes.fromhex("90 50 02 FF")]


async def _discarded(server: SimCameraServer, count: int) -> None:
    while server.discarded_stale_bytes < count:
        await server.output_discarded.wait()
        server.output_discarded.clear()
    assert server.discarded_stale_bytes == count
