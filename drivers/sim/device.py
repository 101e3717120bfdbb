"""Simulated VISCA camera, device side: EVI-D100-like handlers over a timed model of the camera.

The device is sans-IO with explicit time. A transport (the pty server, or the in-process camera
of the unit tests) calls :meth:`ViscaDevice.receive` with the bytes the controller sent and the
time they were read, calls :meth:`ViscaDevice.poll` at (or after) :meth:`ViscaDevice.next_deadline`,
and writes out the :class:`Emission` bytes it gets back. Everything in between is modelled in that
time line:

* **Wire.** With pacing on, each byte takes 10 bit times (8N1) at ``baud`` in both directions; a
  packet is handed over when its last byte has arrived. Byte faults (drop, corrupt, duplicate),
  stalls and garbage from :mod:`drivers.sim.faults` are applied on the wire.
* **One message per video field.** Complete packets wait in a bounded queue; the camera takes one
  per field (1/60 s) at the field boundaries, so a reply comes within ~1 V (docs/design.md §6).
* **Sockets.** Commands that take time (absolute/relative/home/reset moves, Focus/Zoom Direct,
  power-on, One Push AF) hold one of two sockets until their motion ends, then Completion
  ``z0 5y FF``; instant commands (Pan-tiltDrive, Focus Far/Near/Stop, Focus Auto/Manual) get ACK
  and Completion together. A third command while both sockets run gets buffer full
  (``z0 60 03 FF``). A newer command for the same motor supersedes a running one, which then
  completes at once (the motion it asked for has ended). Inquiries need no socket and are answered
  even while both sockets are busy.
* **Errors.** Malformed packets and out-of-range arguments for this model: syntax error
  ``z0 60 02 FF``; packets longer than 16 bytes: message length ``z0 60 01 FF``; manual focus
  commands while AF is on, and motion commands in standby: not executable ``z0 6y 41 FF`` *instead
  of* the ACK, ``y`` being the socket the command would have taken (no socket is held).
* **Motors** move :class:`~drivers.sim.state.CameraState` axes: pan/tilt in degrees at the speed
  table, focus and zoom in counts at finite speeds (defaults below are assumptions: the EVI-D100
  manual gives no motor speeds).

Directions: pan right and tilt up are positive (pan position 0xFA60 is the left end stop); Focus
Far moves towards 0x1000 (far end), Near towards 0x8400.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from drivers.sim.faults import Faults
from drivers.sim.models import EVI_D100 as SIM_EVI_D100
from drivers.sim.models import SimModel
from drivers.sim.state import Axis, CameraState
from drivers.visca import codec, codec_framing, codec_replies, codec_requests
from drivers.visca.codec_framing import Packet
from drivers.visca.codec_replies import (
    Ack,
    AddressSetReply,
    BroadcastEcho,
    Completion,
    ErrorCode,
    ErrorReply,
    InquiryReply,
    NetworkChange,
    Reply,
)

logger = logging.getLogger(__name__)
TRACE = 5  # raw bytes are logged below DEBUG (STYLE §8)

# ---- model constants (EVI-D100-like, design.md §6) ---------------------------------------------

FIELD_PERIOD_S = 1.0 / 60.0  # NTSC field: the camera handles at most one message per field
BITS_PER_BYTE = 10  # 8N1 on the wire: start bit, 8 data bits, stop bit
COUNTS_PER_DEGREE = 14.4  # pan/tilt position counts per degree (EVI-D100)
PAN_LIMIT_COUNTS = 0x05A0  # ±100° (0xFA60–0x05A0)
TILT_LIMIT_COUNTS = 0x0168  # ±25° (0xFE98–0x0168)
MAX_PAN_SPEED_CODE = 0x18
MAX_TILT_SPEED_CODE = 0x14
# deg/s for speed codes 01…18 (index code − 1); tilt uses the first 0x14 entries.
SPEED_TABLE_DEG_S = (
    2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0,
    27.0, 34.0, 42.0, 52.0, 65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0,
)  # fmt: skip
FOCUS_RANGE = (0x1000, 0x8400)  # far end … near end, counts
ZOOM_RANGE = (0x0000, 0x4000)  # wide … tele, counts
# Assumed motor speeds (no datasheet figure): focus sweeps its full range in about 1.5 s, zoom
# goes wide → tele in about 2 s, both typical of the EVI-D100 generation.
DEFAULT_FOCUS_SPEED_COUNTS_S = (FOCUS_RANGE[1] - FOCUS_RANGE[0]) / 1.5
DEFAULT_ZOOM_SPEED_COUNTS_S = (ZOOM_RANGE[1] - ZOOM_RANGE[0]) / 2.0
DEFAULT_POWER_ON_S = 0.1  # standby → on (real cameras take seconds; short keeps tests fast)
# VersionInq identity: Sony's vendor ID is 0x0001; model codes as controllers' tables know them
# (0x040D EVI-D100, 0x040E EVI-D70), so a controller that picks its tables from the model gets
# the camera we simulate.
VENDOR_SONY = 0x0001
MODEL_EVI_D100 = 0x040D
MODEL_EVI_D70 = 0x040E
DEFAULT_ROM = 0x0200
# Packets waiting for their field. A burst larger than this is a controller bug; the camera loses
# the overflow like a real UART receive buffer would.
INPUT_QUEUE_PACKETS = 16
# Reassembler cap: packets of 17…32 bytes are reported as message-length errors, longer runs
# without a terminator are dropped as noise.
RX_REASSEMBLY_CAP = 32
# Bytes still "on the wire" towards the camera (pacing): a UART/pty buffer's worth; a controller
# writing faster than the baud rate loses the excess, as it would on a real line.
RX_WIRE_MAX_BYTES = 4096
# Output bytes not yet handed to the transport (pacing/stalls); beyond this the oldest go.
TX_BACKLOG_PACKETS = 256

Group = Literal["pantilt", "focus", "zoom", "power"]
_MOTOR_GROUPS: tuple[Group, ...] = ("pantilt", "focus", "zoom")
_Targets = tuple[tuple[Axis, float], ...]  # where each axis of a move ends
_Started = tuple[Group, float, _Targets]  # motor group, end time, targets


@dataclass(frozen=True, slots=True)
class DeviceConfig:
    """How the simulated camera behaves; defaults are an EVI-D100 at 9600 baud, no pacing."""

    address: int = 1  # position in the daisy chain: address before Address Set; see Address Set
    baud: int = 9600
    pace: bool = False  # model the wire time of every byte at ``baud`` (10 bits per byte)
    field_period_s: float = FIELD_PERIOD_S
    focus_speed_counts_s: float = DEFAULT_FOCUS_SPEED_COUNTS_S  # Focus Direct / One Push
    zoom_speed_counts_s: float = DEFAULT_ZOOM_SPEED_COUNTS_S  # Zoom Direct
    focus_drive_standard: int = 4  # Focus Far/Near without a speed drive at variable speed p=4
    power_on_s: float = DEFAULT_POWER_ON_S
    autofocus_at_power_up: bool = True  # real cameras come up in AF: drivers must set manual
    network_change_at_power_up: bool = True
    reply_from_a0: bool = False  # firmware quirk (design.md §6): replies carry header A0, not 90
    # Emulator quirk: the broadcast IF_Clear clears the sockets but is not echoed (the spec
    # echoes it); a controller must fall back to each camera's own IF_Clear.
    echo_if_clear_broadcast: bool = True
    camera: SimModel = SIM_EVI_D100  # limits, speeds and identity (drivers/sim/models.py)
    vendor: int | None = None  # VersionInq vendor; None: the camera model's
    model: int | None = None  # VersionInq model code; None: the camera model's
    rom: int = DEFAULT_ROM
    sockets: int = 2

    def __post_init__(self) -> None:
        codec_framing.check_range("address", self.address, 1, 7)
        if self.baud <= 0 or self.field_period_s <= 0:
            raise ValueError("baud and field_period_s must be positive")
        if self.focus_speed_counts_s <= 0 or self.zoom_speed_counts_s <= 0:
            raise ValueError("focus and zoom speeds must be positive (counts per second)")
        codec_framing.check_range("focus_drive_standard", self.focus_drive_standard, 0, 7)
        if self.power_on_s < 0:
            raise ValueError("power_on_s must not be negative")

    @property
    def byte_time_s(self) -> float:
        """Wire time of one byte at ``baud`` (8N1)."""
        return BITS_PER_BYTE / self.baud

    def focus_drive_speed(self, p: int) -> float:
        """Focus Far/Near speed in counts/s for variable speed ``p`` (0 slowest … 7 = Direct)."""
        return self.focus_speed_counts_s * (p + 1) / 8


@dataclass(frozen=True, slots=True)
class Emission:
    """Bytes the camera puts on the wire, and when their last byte has left it."""

    t: float
    data: bytes


@dataclass(slots=True)
class DeviceStats:
    """Counters for tests and the benchmark."""

    packets_in: int = 0
    packets_out: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    errors_out: dict[int, int] = field(default_factory=dict)
    input_overflow: int = 0
    ignored: int = 0  # packets for another address or not from a controller
    lost_completions: int = 0


class ViscaDevice:
    """The camera's protocol engine and motor model, driven by explicit time."""

    def __init__(
        self,
        state: CameraState,
        config: DeviceConfig | None = None,
        faults: Faults | None = None,
        focus_oracle: Callable[[float], float] | None = None,
    ) -> None:
        self.state = state
        self.config = config or DeviceConfig()
        self.camera = self.config.camera
        state.set_limits(
            pan_deg=self.camera.pan_limits_deg,
            tilt_deg=self.camera.tilt_limits_deg,
            focus=self.camera.focus_range,
            zoom=self.camera.zoom_range,
        )
        self.faults = faults or Faults()
        # Where AF would put the focus at time t (the optics simulator may provide it); without
        # it One Push AF leaves the lens where it is.
        self.focus_oracle = focus_oracle
        self.stats = DeviceStats()
        self._address = self.config.address
        self._alive = False  # powered (has a supply): False before power_up and during a cycle
        self._silent = False
        self._connected = True  # the port exists (False while "unplugged")
        self._reassembler = codec_framing.Reassembler(max_packet_len=RX_REASSEMBLY_CAP)
        self._rx_wire: deque[tuple[float, bytes]] = deque()
        self._rx_wire_bytes = 0
        self._rx_free_at = -math.inf
        self._inbox: deque[tuple[float, bytes]] = deque()
        self._last_field = -(2**62)
        self._tx: deque[Emission] = deque()
        self._tx_free_at = -math.inf
        self._events: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = itertools.count()
        self._sockets: dict[int, _Running | None] = dict.fromkeys(codec_framing.SOCKETS)
        self._token = itertools.count(1)
        self._epoch = 0  # bumped by a power cycle: events of the old life are void

    # ---- public API -------------------------------------------------------------------------

    @property
    def address(self) -> int:
        """The camera address now in use (set by Address Set)."""
        return self._address

    @property
    def alive(self) -> bool:
        """True while the camera has power and a port (answers when not silent)."""
        return self._alive and self._connected

    def busy_sockets(self) -> list[int]:
        """Sockets holding a running command."""
        return [s for s, running in self._sockets.items() if running is not None]

    def power_up(self, t: float) -> None:
        """Supply power at ``t``: reset the protocol state, AF per config, send Network Change."""
        self._epoch += 1
        self._alive = True
        self._reset_protocol()
        with self.state.lock:
            self.state.powered = True
            self.state.autofocus = self.config.autofocus_at_power_up
        logger.info("sim camera %d: power up at %.3f", self._address, t)
        if self.config.network_change_at_power_up:
            self._send(NetworkChange(), t)
        self._schedule_periodic(t)

    def power_cycle(self, t: float, off_s: float | None = None) -> None:
        """Lose power at ``t`` (motors stop, buffers lost) and power up ``off_s`` later."""
        off = self.faults.spec.power_off if off_s is None else off_s
        self._power_down(t)
        epoch = self._epoch
        self._schedule(t + off, lambda at: self._power_up_if(epoch, at))

    def disconnect(self, t: float) -> None:
        """The port vanished at ``t``: nothing in or out; the camera loses power with it."""
        self._connected = False
        self._power_down(t)
        self._tx.clear()
        self._rx_wire.clear()
        self._rx_wire_bytes = 0

    def reconnect(self, t: float) -> None:
        """The port is back at ``t``: the camera powers up again (and sends Network Change)."""
        self._connected = True
        self._tx_free_at = self._rx_free_at = t
        self.power_up(t)

    def set_silent(self, silent: bool) -> None:
        """While silent the camera reads its input but never answers (and acts on nothing)."""
        self._silent = silent

    def inject_network_change(self, t: float) -> None:
        """Send an unsolicited Network Change at ``t``."""
        if self.alive:
            self._send(NetworkChange(), t)

    def receive(self, data: bytes, t: float) -> None:
        """Bytes from the controller, read at ``t``."""
        if not data or not self._connected:
            return
        logger.log(TRACE, "sim rx %.4f %s", t, data.hex(" "))
        data = self.faults.mangle(data, "rx")
        if not data:
            return
        if self._rx_wire_bytes + len(data) > RX_WIRE_MAX_BYTES:
            self.stats.input_overflow += 1
            logger.debug("sim camera: receive buffer full, lost %d bytes", len(data))
            return
        self.stats.bytes_in += len(data)
        self._rx_wire_bytes += len(data)
        if self.config.pace:
            start = max(t, self._rx_free_at)
            self._rx_free_at = start + len(data) * self.config.byte_time_s
            self._rx_wire.append((self._rx_free_at, data))
        else:
            self._rx_wire.append((t, data))

    def next_deadline(self) -> float | None:
        """The earliest time at which :meth:`poll` has something to do, or None."""
        candidates = [self._next_internal(), self._tx[0].t if self._tx else None]
        times = [t for t in candidates if t is not None]
        return min(times) if times else None

    def poll(self, t: float) -> list[Emission]:
        """Run the model up to ``t``; return the bytes that have left the camera by then."""
        while (when := self._next_internal()) is not None and when <= t:
            self._step(when)
        out: list[Emission] = []
        while self._tx and self._tx[0].t <= t:
            out.append(self._tx.popleft())
        return out

    # ---- time line --------------------------------------------------------------------------

    def _next_internal(self) -> float | None:
        candidates: list[float] = []
        if self._rx_wire:
            candidates.append(self._rx_wire[0][0])
        if self._inbox:
            candidates.append(self._next_field_time(self._inbox[0][0]))
        if self._events:
            candidates.append(self._events[0][0])
        return min(candidates) if candidates else None

    def _step(self, when: float) -> None:
        # Order at equal times: bytes arrive, scheduled events fire, then the field's message.
        if self._rx_wire and self._rx_wire[0][0] <= when:
            arrived, data = self._rx_wire.popleft()
            self._rx_wire_bytes -= len(data)
            self._on_bytes(data, arrived)
            return
        if self._events and self._events[0][0] <= when:
            at, _, action = heapq.heappop(self._events)
            action(at)
            return
        arrived, raw = self._inbox.popleft()
        field_t = self._next_field_time(arrived)
        self._last_field = round(field_t / self.config.field_period_s)
        self._handle_packet(raw, field_t)

    def _next_field_time(self, arrived: float) -> float:
        period = self.config.field_period_s
        k = max(self._last_field + 1, math.ceil(arrived / period - 1e-9))
        return k * period

    def _schedule(self, t: float, action: Callable[[float], None]) -> None:
        heapq.heappush(self._events, (t, next(self._seq), action))

    def _schedule_periodic(self, t: float) -> None:
        spec = self.faults.spec
        epoch = self._epoch
        if spec.network_change_every is not None:
            every = spec.network_change_every

            def network_change(at: float) -> None:
                if self._epoch == epoch:
                    self.inject_network_change(at)
                    self._schedule(at + every, network_change)

            self._schedule(t + every, network_change)
        if spec.power_cycle_every is not None:
            period = spec.power_cycle_every

            def cycle(at: float) -> None:
                if self._epoch == epoch and self.alive:
                    self.power_cycle(at)

            self._schedule(t + period, cycle)

    def _power_up_if(self, epoch: int, t: float) -> None:
        if self._epoch == epoch and self._connected:
            self.power_up(t)

    def _power_down(self, t: float) -> None:
        self._epoch += 1
        self._alive = False
        with self.state.lock:
            for axis in (self.state.pan, self.state.tilt, self.state.focus, self.state.zoom):
                axis.stop(t)
            self.state.powered = False
        self._reset_protocol()
        logger.info("sim camera %d: power lost at %.3f", self._address, t)

    def _reset_protocol(self) -> None:
        self._sockets = dict.fromkeys(codec_framing.SOCKETS)
        self._inbox.clear()
        self._reassembler.clear()
        self._events.clear()

    # ---- input ------------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, t: float) -> None:
        if not self.alive or self._silent:
            return
        for raw in self._reassembler.feed(data):
            if len(self._inbox) >= INPUT_QUEUE_PACKETS:
                self.stats.input_overflow += 1
                logger.debug("sim camera: input queue full, lost %s", raw.hex(" "))
                continue
            self._inbox.append((t, raw))

    def _handle_packet(self, raw: bytes, t: float) -> None:
        if not self.alive or self._silent:
            return
        self.stats.packets_in += 1
        header = raw[0]
        receiver = header & 0x0F
        sender = (header >> 4) & 0x07
        if sender != codec_framing.CONTROLLER_ADDRESS or receiver not in (
            self._address,
            codec_framing.BROADCAST_ADDRESS,
        ):
            self.stats.ignored += 1
            return
        if len(raw) > codec_framing.MAX_PACKET_LEN:
            self._send(ErrorReply(0, ErrorCode.MESSAGE_LENGTH), t)
            return
        if len(raw) == 3 and raw[1] >> 4 == 0x2 and raw[1] & 0x0F not in codec_framing.SOCKETS:
            # Cancel of a socket this camera does not have: "no socket" for that socket number
            # (z0 6y 05 FF), as the VISCA spec answers it, not a syntax error.
            self._send(ErrorReply(raw[1] & 0x0F, ErrorCode.NO_SOCKET), t)
            return
        try:
            packet = Packet.from_bytes(raw)
            if receiver == codec_framing.BROADCAST_ADDRESS and _is_address_set(packet.message):
                self._address_set(packet.message[1], t)
                return
            request = codec.decode_request(packet)
            _check_model_ranges(request, self.camera)
        except ValueError as exc:  # CodecError, or out of range for this model
            logger.debug("sim camera: syntax error for %s: %s", raw.hex(" "), exc)
            self._send(ErrorReply(0, ErrorCode.SYNTAX), t)
            return
        logger.debug("sim camera %d: %s at %.4f", self._address, request, t)
        self._dispatch(request, t)

    def _dispatch(self, request: codec_requests.Request, t: float) -> None:
        match request:
            case codec_requests.IFClearBroadcast():
                self._clear_sockets(t)
                if self.config.echo_if_clear_broadcast:
                    self._send(BroadcastEcho(request.to_message()), t)
            case codec_requests.IFClear():
                self._clear_sockets(t)
                self._send(InquiryReply(b""), t)
            # normally handled before decoding; kept for completeness
            case codec_requests.AddressSet():
                self._address_set(0x01, t)
            case codec_requests.Cancel():
                self._cancel(request.socket, t)
            case (
                codec_requests.FocusPositionInquiry()
                | codec_requests.ZoomPositionInquiry()
                | codec_requests.FocusModeInquiry()
                | codec_requests.PowerInquiry()
                | codec_requests.PanTiltPositionInquiry()
                | codec_requests.PanTiltMaxSpeedInquiry()
                | codec_requests.VersionInquiry()
            ):
                self._send(InquiryReply(self._inquiry_data(request, t)), t)
            case _:
                self._command(request, t)

    # ---- handlers ---------------------------------------------------------------------------

    def _address_set(self, given: int, t: float) -> None:
        # The cameras before this one in the chain took given … given + address − 2.
        mine = min(given + self.config.address - 1, codec_framing.MAX_CAMERA_ADDRESS)
        self._address = mine
        self._send(AddressSetReply(next_address=mine + 1), t)

    def _clear_sockets(self, t: float) -> None:
        # IF_Clear empties the command buffers: running commands end without a reply.
        for socket, running in self._sockets.items():
            if running is not None:
                self._stop_group(running.group, t)
                self._sockets[socket] = None

    def _cancel(self, socket: int, t: float) -> None:
        running = self._sockets[socket]
        if running is None:
            self._send(ErrorReply(socket, ErrorCode.NO_SOCKET), t)
            return
        self._stop_group(running.group, t)
        self._sockets[socket] = None
        self._send(ErrorReply(socket, ErrorCode.CANCELLED), t)

    def _inquiry_data(self, request: codec_requests.Request, t: float) -> bytes:
        st = self.state
        with st.lock:
            match request:
                case codec_requests.FocusPositionInquiry():
                    return codec_replies.FocusPosition(round(st.focus.position(t))).to_data()
                case codec_requests.ZoomPositionInquiry():
                    return codec_replies.ZoomPosition(round(st.zoom.position(t))).to_data()
                case codec_requests.FocusModeInquiry():
                    return codec_replies.FocusModeState(auto=st.autofocus).to_data()
                case codec_requests.PowerInquiry():
                    return codec_replies.PowerState(on=st.powered).to_data()
                case codec_requests.PanTiltPositionInquiry():
                    return codec_replies.PanTiltPosition(
                        pan=round(st.pan.position(t) * self.camera.pan_counts_per_deg),
                        tilt=round(st.tilt.position(t) * self.camera.tilt_counts_per_deg),
                    ).to_data()
                case codec_requests.PanTiltMaxSpeedInquiry():
                    cam = self.camera
                    return codec_replies.PanTiltMaxSpeed(
                        cam.max_pan_speed_code, cam.max_tilt_speed_code
                    ).to_data()
                case codec_requests.VersionInquiry():
                    cfg = self.config
                    vendor = self.camera.vendor if cfg.vendor is None else cfg.vendor
                    model = self.camera.model if cfg.model is None else cfg.model
                    return codec_replies.Version(vendor, model, cfg.rom, cfg.sockets).to_data()
        raise AssertionError(f"not an inquiry: {request!r}")

    def _command(self, request: codec_requests.Request, t: float) -> None:
        free = [s for s, running in self._sockets.items() if running is None]
        if not free:
            self._send(ErrorReply(0, ErrorCode.BUFFER_FULL), t)
            return
        socket = free[0]
        st = self.state
        if not st.powered and not isinstance(request, codec_requests.CamPower):
            self._send(ErrorReply(socket, ErrorCode.NOT_EXECUTABLE), t)
            return
        manual_focus = (
            codec_requests.FocusDrive,
            codec_requests.FocusDirect,
            codec_requests.FocusOnePush,
        )
        if st.autofocus and isinstance(request, manual_focus):
            self._send(ErrorReply(socket, ErrorCode.NOT_EXECUTABLE), t)
            return
        self._send(Ack(socket), t)
        with st.lock:
            done = self._execute(request, t)
        if done is None:  # instant command: ACK and Completion together
            self._complete(socket, t)
            return
        group, finish, targets = done
        token = next(self._token)
        self._sockets[socket] = _Running(token, group, targets)
        # The camera notices the end of a move at a field boundary.
        period = self.config.field_period_s
        finish_field = max(t, math.ceil(finish / period - 1e-9) * period)
        self._schedule(finish_field, lambda at: self._finish(socket, token, at))

    def _execute(self, request: codec_requests.Request, t: float) -> _Started | None:
        """Start the physical effect; return (group, end time, final positions) or None."""
        st = self.state
        cfg = self.config
        match request:
            case codec_requests.CamPower(on=on):
                self._supersede("power", t)
                if on and not st.powered:
                    return "power", t + cfg.power_on_s, ()
                if not on and st.powered:
                    for group in _MOTOR_GROUPS:
                        self._supersede(group, t)
                        self._stop_group(group, t)
                    st.powered = False
                return None
            case codec_requests.FocusMode(auto=auto):
                if auto:
                    self._supersede("focus", t)
                    self._stop_group("focus", t)
                st.autofocus = auto
                return None
            case codec_requests.FocusDrive(direction=direction, speed=speed):
                self._supersede("focus", t)
                if direction is codec_requests.FocusDirection.STOP:
                    st.focus.stop(t)
                else:
                    p = cfg.focus_drive_standard if speed is None else speed
                    sign = -1 if direction is codec_requests.FocusDirection.FAR else 1
                    st.focus.drive(sign, cfg.focus_drive_speed(p), t)
                return None
            case codec_requests.FocusDirect(counts=counts):
                self._supersede("focus", t)
                end = st.focus.move_to(counts, cfg.focus_speed_counts_s, t)
                return "focus", end, ((st.focus, counts),)
            case codec_requests.FocusOnePush():
                self._supersede("focus", t)
                here = st.focus.position(t)
                target = here if self.focus_oracle is None else self.focus_oracle(t)
                target = _clamp(st.focus, target)
                end = st.focus.move_to(target, cfg.focus_speed_counts_s, t)
                return "focus", end, ((st.focus, target),)
            case codec_requests.ZoomDirect(counts=counts):
                self._supersede("zoom", t)
                end = st.zoom.move_to(counts, cfg.zoom_speed_counts_s, t)
                return "zoom", end, ((st.zoom, counts),)
            case codec_requests.PanTiltDrive():
                self._supersede("pantilt", t)
                _drive(st, request, t, self.camera)
                return None
            case codec_requests.PanTiltAbsolute() | codec_requests.PanTiltRelative():
                self._supersede("pantilt", t)
                pan_deg = request.pan / self.camera.pan_counts_per_deg
                tilt_deg = request.tilt / self.camera.tilt_counts_per_deg
                if isinstance(request, codec_requests.PanTiltRelative):
                    pan_deg = _clamp(st.pan, pan_deg + st.pan.position(t))
                    tilt_deg = _clamp(st.tilt, tilt_deg + st.tilt.position(t))
                end = max(
                    st.pan.move_to(pan_deg, _pan_speed(self.camera, request.pan_speed), t),
                    st.tilt.move_to(tilt_deg, _tilt_speed(self.camera, request.tilt_speed), t),
                )
                return "pantilt", end, ((st.pan, pan_deg), (st.tilt, tilt_deg))
            case codec_requests.PanTiltHome():
                self._supersede("pantilt", t)
                return "pantilt", _move_pan_tilt(st, 0.0, 0.0, t, self.camera), _home(st)
            case codec_requests.PanTiltReset():
                # Runs to the lower end stops, then home, at full speed.
                self._supersede("pantilt", t)
                leg = _move_pan_tilt(st, st.pan.low, st.tilt.low, t, self.camera)
                first = (st.pan.arrival_time(), st.tilt.arrival_time())

                def second_leg(at: float) -> None:
                    # Only if nothing (cancel, a newer move, power loss) replaced the first leg.
                    with st.lock:
                        if (st.pan.arrival_time(), st.tilt.arrival_time()) == first:
                            _move_pan_tilt(st, 0.0, 0.0, at, self.camera)

                self._schedule(leg, second_leg)
                return "pantilt", leg + _travel_s(st.pan.low, st.tilt.low, self.camera), _home(st)
        raise AssertionError(f"unhandled command {request!r}")

    def _finish(self, socket: int, token: int, t: float) -> None:
        running = self._sockets[socket]
        if running is None or running.token != token:
            return  # cancelled, cleared or superseded meanwhile
        with self.state.lock:
            if running.group == "power":
                self.state.powered = True
            # Land exactly on the target: t·v sums leave float dust (6144.0000000005 counts).
            for axis, target in running.targets:
                if not axis.moving(t):
                    axis.jump(target, t)
        self._sockets[socket] = None
        self._complete(socket, t)

    def _supersede(self, group: Group, t: float) -> None:
        # A newer command for the same motor ends the running one: its motion is over.
        for socket, running in self._sockets.items():
            if running is not None and running.group == group:
                self._sockets[socket] = None
                self._complete(socket, t)

    def _stop_group(self, group: Group, t: float) -> None:
        st = self.state
        with st.lock:
            if group == "pantilt":
                st.pan.stop(t)
                st.tilt.stop(t)
            elif group == "focus":
                st.focus.stop(t)
            elif group == "zoom":
                st.zoom.stop(t)

    def _complete(self, socket: int, t: float) -> None:
        if self.faults.lose_completion():
            self.stats.lost_completions += 1
            logger.debug("fault: Completion for socket %d lost", socket)
            return
        self._send(Completion(socket), t)

    # ---- output -----------------------------------------------------------------------------

    def _send(self, reply: Reply, t: float) -> None:
        if not self.alive or self._silent:
            return
        data = codec.encode_reply(reply, self._address)
        if self.config.reply_from_a0 and data[0] != 0x88:
            data = b"\xa0" + data[1:]
        if isinstance(reply, ErrorReply):
            self.stats.errors_out[reply.code] = self.stats.errors_out.get(reply.code, 0) + 1
        self.stats.packets_out += 1
        stall = self.faults.stall_s()
        wire = self.faults.mangle(self.faults.garbage() + data, "tx")
        start = max(t, self._tx_free_at) + stall
        end = start + len(wire) * self.config.byte_time_s if self.config.pace else start
        self._tx_free_at = end
        if not wire:
            return
        self.stats.bytes_out += len(wire)
        if len(self._tx) >= TX_BACKLOG_PACKETS:
            self._tx.popleft()
        logger.log(TRACE, "sim tx %.4f %s", end, wire.hex(" "))
        self._tx.append(Emission(end, wire))


class VirtualClock:
    """A clock that only moves when told to: lock-step tests and fast benchmarks."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = start

    def __call__(self) -> float:
        """The current virtual time in seconds."""
        return self._now

    def set(self, t: float) -> None:
        """Move to ``t`` (never backwards)."""
        if t < self._now:
            raise ValueError(f"virtual clock cannot go back from {self._now} to {t}")
        self._now = t

    def advance(self, dt: float) -> float:
        """Move forward by ``dt`` seconds; return the new time."""
        self.set(self._now + dt)
        return self._now


@dataclass(slots=True)
class _Running:
    token: int
    group: Group
    targets: _Targets


def _home(st: CameraState) -> _Targets:
    return ((st.pan, 0.0), (st.tilt, 0.0))


def _clamp(axis: Axis, value: float) -> float:
    return min(axis.high, max(axis.low, value))


def speed_deg_s(code: int) -> float:
    """Pan/tilt speed in degrees per second for speed code 01…18."""
    codec_framing.check_range("speed code", code, 1, len(SPEED_TABLE_DEG_S))
    return SPEED_TABLE_DEG_S[code - 1]


def _is_address_set(message: bytes) -> bool:
    # ``30 0w``: w is the first free address; a camera further down the chain sees w > 1, which
    # the codec's AddressSet (always 30 01, as the controller sends it) does not parse.
    return len(message) == 2 and message[0] == 0x30 and 1 <= message[1] <= 7


def _check_model_ranges(request: codec_requests.Request, cam: SimModel) -> None:
    """Raise ValueError for arguments the wire format allows but the camera model does not."""
    pan_codes, tilt_codes = cam.max_pan_speed_code, cam.max_tilt_speed_code
    match request:
        case codec_requests.FocusDirect(counts=counts):
            codec_framing.check_range("focus counts", counts, *cam.focus_range)
        case codec_requests.ZoomDirect(counts=counts):
            codec_framing.check_range("zoom counts", counts, *cam.zoom_range)
        case codec_requests.PanTiltDrive(pan_speed=pan_speed, tilt_speed=tilt_speed):
            codec_framing.check_range("pan speed", pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", tilt_speed, 1, tilt_codes)
        case codec_requests.PanTiltAbsolute():
            codec_framing.check_range("pan speed", request.pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", request.tilt_speed, 1, tilt_codes)
            codec_framing.check_range("pan position", request.pan, *cam.pan_limit_counts)
            codec_framing.check_range("tilt position", request.tilt, *cam.tilt_limit_counts)
        case codec_requests.PanTiltRelative():
            codec_framing.check_range("pan speed", request.pan_speed, 1, pan_codes)
            codec_framing.check_range("tilt speed", request.tilt_speed, 1, tilt_codes)
            pan_low, pan_high = cam.pan_limit_counts
            tilt_low, tilt_high = cam.tilt_limit_counts
            span_pan, span_tilt = pan_high - pan_low, tilt_high - tilt_low
            codec_framing.check_range("pan offset", request.pan, -span_pan, span_pan)
            codec_framing.check_range("tilt offset", request.tilt, -span_tilt, span_tilt)
        case _:
            pass


def _pan_speed(cam: SimModel, code: int) -> float:
    codec_framing.check_range("pan speed code", code, 1, cam.max_pan_speed_code)
    return cam.pan_speeds_deg_s[code - 1]


def _tilt_speed(cam: SimModel, code: int) -> float:
    codec_framing.check_range("tilt speed code", code, 1, cam.max_tilt_speed_code)
    return cam.tilt_speeds_deg_s[code - 1]


def _drive(st: CameraState, request: codec_requests.PanTiltDrive, t: float, cam: SimModel) -> None:
    pan_dir = {codec_requests.PanDirection.LEFT: -1, codec_requests.PanDirection.RIGHT: 1}.get(
        request.pan
    )
    tilt_dir = {codec_requests.TiltDirection.DOWN: -1, codec_requests.TiltDirection.UP: 1}.get(
        request.tilt
    )
    if pan_dir is None:
        st.pan.stop(t)
    else:
        st.pan.drive(pan_dir, _pan_speed(cam, request.pan_speed), t)
    if tilt_dir is None:
        st.tilt.stop(t)
    else:
        st.tilt.drive(tilt_dir, _tilt_speed(cam, request.tilt_speed), t)


def _move_pan_tilt(
    st: CameraState, pan_deg: float, tilt_deg: float, t: float, cam: SimModel
) -> float:
    return max(
        st.pan.move_to(pan_deg, cam.pan_speeds_deg_s[-1], t),
        st.tilt.move_to(tilt_deg, cam.tilt_speeds_deg_s[-1], t),
    )


def _travel_s(pan_deg: float, tilt_deg: float, cam: SimModel) -> float:
    return max(abs(pan_deg) / cam.pan_speeds_deg_s[-1], abs(tilt_deg) / cam.tilt_speeds_deg_s[-1])
