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
* **Motors** move :class:`~drivers.sim.state.CameraState` axes: pan/tilt in degrees at the camera
  model's speed tables, focus and zoom in counts at finite speeds (the defaults in
  :mod:`drivers.sim.device_types` are assumptions: the EVI-D100 manual gives no motor speeds).

Directions: pan right and tilt up are positive (pan position 0xFA60 is the left end stop); Focus
Far moves towards 0x1000 (far end), Near towards 0x8400.

The device's constants, :class:`~drivers.sim.device_types.DeviceConfig`, the
:class:`~drivers.sim.device_types.Emission` and the counters live in
:mod:`drivers.sim.device_types` (import them from there); the camera model's facts (limits,
speed tables, identity) in :mod:`drivers.sim.models`; the motors' limits and moves for the
camera model in :mod:`drivers.sim.device_motors`. What is left is the one class
:class:`ViscaDevice` (~515 lines), a little past ~600 lines with its imports: its wire, time line,
input, handlers and output share the sockets, the event heap, the queues and the power epoch, and
are one sans-IO engine.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from drivers.sim.device_motors import (
    check_model_ranges,
    drive_pan_tilt,
    move_pan_tilt,
    pan_speed_deg_s,
    tilt_speed_deg_s,
    travel_s,
)
from drivers.sim.device_types import DeviceConfig, DeviceStats, Emission
from drivers.sim.faults import Faults
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

# ---- buffers -------------------------------------------------------------------------------------

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
            check_model_ranges(request, self.camera)
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
                drive_pan_tilt(st, request, t, self.camera)
                return None
            case codec_requests.PanTiltAbsolute() | codec_requests.PanTiltRelative():
                self._supersede("pantilt", t)
                pan_deg = request.pan / self.camera.pan_counts_per_deg
                tilt_deg = request.tilt / self.camera.tilt_counts_per_deg
                if isinstance(request, codec_requests.PanTiltRelative):
                    pan_deg = _clamp(st.pan, pan_deg + st.pan.position(t))
                    tilt_deg = _clamp(st.tilt, tilt_deg + st.tilt.position(t))
                end = max(
                    st.pan.move_to(pan_deg, pan_speed_deg_s(self.camera, request.pan_speed), t),
                    st.tilt.move_to(tilt_deg, tilt_speed_deg_s(self.camera, request.tilt_speed), t),
                )
                return "pantilt", end, ((st.pan, pan_deg), (st.tilt, tilt_deg))
            case codec_requests.PanTiltHome():
                self._supersede("pantilt", t)
                return "pantilt", move_pan_tilt(st, 0.0, 0.0, t, self.camera), _home(st)
            case codec_requests.PanTiltReset():
                # Runs to the lower end stops, then home, at full speed.
                self._supersede("pantilt", t)
                leg = move_pan_tilt(st, st.pan.low, st.tilt.low, t, self.camera)
                first = (st.pan.arrival_time(), st.tilt.arrival_time())

                def second_leg(at: float) -> None:
                    # Only if nothing (cancel, a newer move, power loss) replaced the first leg.
                    with st.lock:
                        if (st.pan.arrival_time(), st.tilt.arrival_time()) == first:
                            move_pan_tilt(st, 0.0, 0.0, at, self.camera)

                self._schedule(leg, second_leg)
                return "pantilt", leg + travel_s(st.pan.low, st.tilt.low, self.camera), _home(st)
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


@dataclass(slots=True)
class _Running:
    token: int
    group: Group
    targets: _Targets


def _home(st: CameraState) -> _Targets:
    return ((st.pan, 0.0), (st.tilt, 0.0))


def _clamp(axis: Axis, value: float) -> float:
    return min(axis.high, max(axis.low, value))


def _is_address_set(message: bytes) -> bool:
    # ``30 0w``: w is the first free address; a camera further down the chain sees w > 1, which
    # the codec's AddressSet (always 30 01, as the controller sends it) does not parse.
    return len(message) == 2 and message[0] == 0x30 and 1 <= message[1] <= 7
