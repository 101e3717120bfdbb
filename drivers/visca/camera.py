"""Typed async camera API in user units (degrees, deg/s, counts) over a :class:`ViscaLink`.

One :class:`Camera` per camera address (1–7); several share one link on a daisy chain. Unit
conversion goes through a :class:`CameraProfile` (:mod:`drivers.visca.profiles`: EVI-D100 by
default, EVI-D70, and an SRG-300-like VISCA-over-IP head). Every argument is checked against the
profile *before* a byte is sent (``ValueError`` naming the field and its range). Idempotent
operations (inquiries, absolute/direct moves, stops, modes) are retried ``retries`` times after a
timeout or a Network Change; relative moves never are (a lost ACK could mean the camera already
moved).

Directions follow the VISCA convention used by the simulator: pan right and tilt up positive.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from typing import Literal, TypeVar

from drivers.visca.codec_framing import check_range
from drivers.visca.codec_replies import Version
from drivers.visca.codec_requests import (
    CamPower,
    Command,
    FocusDirect,
    FocusDirection,
    FocusDrive,
    FocusMode,
    FocusModeInquiry,
    FocusPositionInquiry,
    IFClear,
    PanDirection,
    PanTiltAbsolute,
    PanTiltDrive,
    PanTiltHome,
    PanTiltPositionInquiry,
    PanTiltRelative,
    PowerInquiry,
    TiltDirection,
    VersionInquiry,
    ZoomDirect,
    ZoomPositionInquiry,
)
from drivers.visca.errors import (
    ViscaError,
    ViscaMessageLengthError,
    ViscaNetworkChangeError,
    ViscaSyntaxError,
    ViscaTimeoutError,
)
from drivers.visca.link_api import CommandHandle, LinkApi
from drivers.visca.profiles import (
    EVI_D70,
    EVI_D100,
    PROFILES,
    SRG_300,
    CameraProfile,
    SpeedCode,
    check_degrees,
    nearest_speed_code,
    profile_for,
    profile_for_version,
)
from drivers.visca.session_types import FIELD_S, POWER_COMPLETION_TIMEOUT_S

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_RETRIES",
    "EVI_D70",
    "EVI_D100",
    "IP_COMPLETION_PROBE_S",
    "MOVE_TIMEOUT_FACTOR",
    "MOVE_TIMEOUT_MARGIN_S",
    "PROFILES",
    "SRG_300",
    "Camera",
    "CameraProfile",
    "SpeedCode",
    "profile_for",
    "profile_for_version",
]

T = TypeVar("T")

# Move Completion timeouts: the camera's travel time times a tolerance on the motor speed
# (tables are nominal; ±20% covers load and temperature), plus the time to notice the end at a
# field boundary and get the Completion over the wire, with margin.
MOVE_TIMEOUT_FACTOR = 1.25
MOVE_TIMEOUT_MARGIN_S = 1.0
# Early-Completion models: poll FocusPosInq until the lens stops, at most this long after the
# Completion, one inquiry every two fields (the camera answers one message per field).
FOCUS_SETTLE_TIMEOUT_S = 1.0
FOCUS_POLL_PERIOD_S = 2 * FIELD_S
# VISCA over IP: a move silent this long is checked by a position inquiry (a lost Completion
# is then recovered in ~0.5 s instead of the move's whole timeout, 3.5 s for a focus move).
# Half a second is ~15 fields: far longer than a Completion's round trip on a LAN.
IP_COMPLETION_PROBE_S = 0.5
DEFAULT_RETRIES = 1  # retries of an idempotent operation after a timeout or Network Change


class Camera:
    """One VISCA camera at ``address`` on ``link``, in user units."""

    def __init__(
        self,
        link: LinkApi,
        address: int = 1,
        profile: CameraProfile = EVI_D100,
        *,
        retries: int = DEFAULT_RETRIES,
        move_timeout_margin_s: float = MOVE_TIMEOUT_MARGIN_S,
        adopt_profile: bool = True,
        completion_probe_s: float | None = None,
    ) -> None:
        check_range("camera address", address, 1, 7)
        self.link = link
        self.address = address
        self.profile = profile
        # At initialise, switch to the profile of the model the camera identifies as (its real
        # limits); False keeps ``profile`` whatever the camera says (both warn on a mismatch).
        self.adopt_profile = adopt_profile
        # Check a move by inquiry after this much silence (None: IP_COMPLETION_PROBE_S on VISCA
        # over IP, never on serial and TCP, which do not lose packets; 0: never).
        self.completion_probe_s = completion_probe_s
        self.completions_inferred = 0  # moves ended by inquiry after a lost Completion
        self.retries = retries
        self.move_timeout_margin_s = move_timeout_margin_s
        self.version_info: Version | None = None

    # ---- set-up -------------------------------------------------------------------------------

    async def initialize(self) -> Version:
        """Address Set + IF_Clear, power on if in standby, read the version, manual focus.

        Registers itself to run again, behind the link's gate, after a reconnect or Network
        Change.
        """
        version = await self._setup()
        self.link.add_reinit_step(self._reinit_step)
        return version

    async def version(self) -> Version:
        """VersionInq: vendor, model, ROM and number of sockets."""
        return await self._retry(lambda: self.link.inquire(self.address, VersionInquiry()))

    async def power(self, on: bool) -> None:
        """CAM_Power on or standby (returns when the camera has finished switching)."""
        await self._command(CamPower(on=on), POWER_COMPLETION_TIMEOUT_S)

    async def power_is_on(self) -> bool:
        """PowerInq."""
        answer = await self._retry(lambda: self.link.inquire(self.address, PowerInquiry()))
        return answer.on

    # ---- focus ------------------------------------------------------------------------------

    async def start_focus_direct(self, counts: int) -> CommandHandle:
        """Send Focus Direct and return its handle (ACK and Completion awaited by the caller)."""
        request = FocusDirect(self.profile.check_focus(counts))
        return self.link.submit(self.address, request, completion_timeout=self._focus_timeout_s())

    async def focus_direct(self, counts: int) -> None:
        """Move the focus to ``counts``; return once the lens has stopped."""
        request = FocusDirect(self.profile.check_focus(counts))

        async def reached() -> bool:
            return await self.focus_position() == counts

        await self._command(request, self._focus_timeout_s(), reached)
        if self.profile.focus_completion_early:
            await self._wait_focus_settled(counts)

    async def focus_position(self) -> int:
        """FocusPosInq in counts."""
        answer = await self._retry(lambda: self.link.inquire(self.address, FocusPositionInquiry()))
        return answer.counts

    async def focus_mode(self, auto: bool) -> None:
        """Focus Auto (True) or Manual (False)."""
        await self._command(FocusMode(auto=auto))

    async def focus_is_auto(self) -> bool:
        """FocusModeInq."""
        answer = await self._retry(lambda: self.link.inquire(self.address, FocusModeInquiry()))
        return answer.auto

    async def focus_drive(
        self, direction: Literal["far", "near", "stop"], speed: int | None = None
    ) -> None:
        """Focus Far/Near (continuous, variable ``speed`` 0–7 or the standard speed) or Stop."""
        directions = {
            "far": FocusDirection.FAR,
            "near": FocusDirection.NEAR,
            "stop": FocusDirection.STOP,
        }
        if direction not in directions:
            raise ValueError(f"direction must be one of far, near, stop; got {direction!r}")
        if speed is not None:
            check_range("speed", speed, 0, 7)
        await self._command(FocusDrive(directions[direction], speed))

    async def focus_stop(self) -> None:
        """Focus Stop (jumps the queue)."""
        await self._command(FocusDrive(FocusDirection.STOP))

    # ---- zoom -------------------------------------------------------------------------------

    async def zoom_direct(self, counts: int) -> None:
        """Move the zoom to ``counts``; return once it has stopped."""
        request = ZoomDirect(self.profile.check_zoom(counts))
        timeout = self.profile.zoom_full_travel_s * MOVE_TIMEOUT_FACTOR + self.move_timeout_margin_s

        async def reached() -> bool:
            return await self.zoom_position() == counts

        await self._command(request, timeout, reached)

    async def zoom_position(self) -> int:
        """ZoomPosInq in counts."""
        answer = await self._retry(lambda: self.link.inquire(self.address, ZoomPositionInquiry()))
        return answer.counts

    # ---- pan/tilt ---------------------------------------------------------------------------

    async def pan_tilt_absolute(
        self,
        pan_deg: float,
        tilt_deg: float,
        speed: float | SpeedCode | None = None,
        tilt_speed: float | SpeedCode | None = None,
    ) -> None:
        """Move to (pan_deg, tilt_deg); ``speed`` in deg/s or a SpeedCode (None: fastest).

        ``tilt_speed`` defaults to ``speed`` (capped at the fastest tilt). Returns on arrival.
        """
        request, timeout = self._pan_tilt_move(
            PanTiltAbsolute, pan_deg, tilt_deg, speed, tilt_speed
        )
        assert isinstance(request, PanTiltAbsolute)
        target = (request.pan, request.tilt)

        async def reached() -> bool:
            pan, tilt = await self.pan_tilt_position()
            p = self.profile
            return (
                round(pan * p.pan_counts_per_deg),
                round(tilt * p.tilt_counts_per_deg),
            ) == target

        await self._command(request, timeout, reached)

    async def start_pan_tilt_absolute(
        self,
        pan_deg: float,
        tilt_deg: float,
        speed: float | SpeedCode | None = None,
        tilt_speed: float | SpeedCode | None = None,
    ) -> CommandHandle:
        """Send an absolute move and return its handle."""
        request, timeout = self._pan_tilt_move(
            PanTiltAbsolute, pan_deg, tilt_deg, speed, tilt_speed
        )
        return self.link.submit(self.address, request, completion_timeout=timeout)

    async def pan_tilt_relative(
        self,
        pan_deg: float,
        tilt_deg: float,
        speed: float | SpeedCode | None = None,
        tilt_speed: float | SpeedCode | None = None,
    ) -> None:
        """Move by (pan_deg, tilt_deg) from where the head is; never retried."""
        request, timeout = self._pan_tilt_move(
            PanTiltRelative, pan_deg, tilt_deg, speed, tilt_speed
        )
        await self.link.command(self.address, request, completion_timeout=timeout)

    async def pan_tilt_drive(self, pan_speed_deg_s: float, tilt_speed_deg_s: float) -> None:
        """Turn continuously at signed speeds (right/up positive; 0 stops that axis)."""
        profile = self.profile
        pan_dir, pan_code = _drive_axis(
            "pan_speed_deg_s", pan_speed_deg_s, profile.pan_speeds_deg_s, profile.name,
            (PanDirection.RIGHT, PanDirection.LEFT, PanDirection.STOP),
        )  # fmt: skip
        tilt_dir, tilt_code = _drive_axis(
            "tilt_speed_deg_s", tilt_speed_deg_s, profile.tilt_speeds_deg_s, profile.name,
            (TiltDirection.UP, TiltDirection.DOWN, TiltDirection.STOP),
        )  # fmt: skip
        request = PanTiltDrive(pan_code, tilt_code, PanDirection(pan_dir), TiltDirection(tilt_dir))
        await self._command(request)

    async def pan_tilt_stop(self) -> None:
        """Stop pan and tilt now (a running absolute/relative/home move is cancelled first)."""
        running = self.link.running(self.address)
        moves = [
            s for s, r in running.items()
            if isinstance(r, PanTiltAbsolute | PanTiltRelative | PanTiltHome)
        ]  # fmt: skip
        if moves and len(running) >= 2:
            # Both sockets busy: the Stop would wait for one (or draw buffer full); free the
            # socket of the pan/tilt move, which ends that move anyway.
            for socket in moves:
                await self.link.cancel(self.address, socket)
        await self._command(PanTiltDrive.stop())

    async def pan_tilt_position(self) -> tuple[float, float]:
        """Pan-tiltPosInq in degrees (pan, tilt)."""
        answer = await self._retry(
            lambda: self.link.inquire(self.address, PanTiltPositionInquiry())
        )
        return (
            answer.pan / self.profile.pan_counts_per_deg,
            answer.tilt / self.profile.tilt_counts_per_deg,
        )

    async def home(self) -> None:
        """Pan/tilt to the home position (0°, 0°)."""
        p = self.profile
        span = max(
            p.pan_range_deg[1] - p.pan_range_deg[0], p.tilt_range_deg[1] - p.tilt_range_deg[0]
        )
        timeout = span / p.home_speed_deg_s * MOVE_TIMEOUT_FACTOR + self.move_timeout_margin_s
        await self._command(PanTiltHome(), timeout)

    async def cancel(self, socket: int) -> bool:
        """Cancel the command in ``socket``; True if one was running there."""
        return await self.link.cancel(self.address, socket)

    # ---- internals ----------------------------------------------------------------------------

    async def _command(
        self,
        request: Command,
        completion_timeout: float | None = None,
        reached: Callable[[], Awaitable[bool]] | None = None,
    ) -> None:
        probe_s = self._probe_s()
        if reached is None or probe_s is None:
            await self._retry(
                lambda: self.link.command(
                    self.address, request, completion_timeout=completion_timeout
                )
            )
            return

        async def probed() -> None:
            # On a lossy link a Completion can be lost after its ACK; rather than wait the whole
            # move timeout, ask where the axis is after each PROBE of silence: at the target,
            # the move is over and its Completion was lost.
            handle = self.link.submit(self.address, request, completion_timeout=completion_timeout)
            await handle.acked()
            while True:
                try:
                    async with asyncio.timeout(probe_s):
                        await handle.completed()
                    return
                except TimeoutError:
                    if handle.done():
                        await handle.completed()
                        return
                if await reached():
                    if self.link.completion_inferred(handle):
                        self.completions_inferred += 1
                        logger.info(
                            "camera %d: %s reached its target but no Completion came (lost on "
                            "the network); taken as completed",
                            self.address, type(request).__name__,
                        )  # fmt: skip
                    return

        await self._retry(probed)

    def _probe_s(self) -> float | None:
        """Silence after which a running move is checked by inquiry (None: never)."""
        if self.completion_probe_s is not None:
            return self.completion_probe_s if self.completion_probe_s > 0 else None
        return IP_COMPLETION_PROBE_S if self.link.url.startswith("visca-ip://") else None

    async def _retry(self, operation: Callable[[], Awaitable[T]]) -> T:
        attempt = 0
        while True:
            try:
                return await operation()
            except (ViscaTimeoutError, ViscaNetworkChangeError) as exc:
                if attempt >= self.retries:
                    raise
                attempt += 1
                logger.debug("camera %d: retrying after %s", self.address, exc)
            except (ViscaSyntaxError, ViscaMessageLengthError) as exc:
                raise exc.with_hint(self._device_side_hint()) from exc

    def _device_side_hint(self) -> str:
        """Advice for a syntax or length error on a request this API checked before sending."""
        who = ""
        if self.version_info is not None:
            v = self.version_info
            known = profile_for_version(v.vendor, v.model)
            named = f", the {known.name}" if known is not None else ", a model unknown to dffd"
            who = f" (it identifies as vendor 0x{v.vendor:04X} model 0x{v.model:04X}{named})"
        return (
            f"every value was checked against the {self.profile.name} profile before it was "
            f"sent, so the device is the likely side at fault: its firmware does not implement "
            f"the command this way, or it is not a {self.profile.name}{who}; check camera.model "
            "and the camera's manual (the raw packets are in the DEBUG log)"
        )

    def _focus_timeout_s(self) -> float:
        return self.profile.focus_full_travel_s * MOVE_TIMEOUT_FACTOR + self.move_timeout_margin_s

    def _pan_tilt_move(
        self,
        kind: type[PanTiltAbsolute] | type[PanTiltRelative],
        pan_deg: float,
        tilt_deg: float,
        speed: float | SpeedCode | None,
        tilt_speed: float | SpeedCode | None,
    ) -> tuple[PanTiltAbsolute | PanTiltRelative, float]:
        p = self.profile
        pan_span = p.pan_range_deg[1] - p.pan_range_deg[0]
        tilt_span = p.tilt_range_deg[1] - p.tilt_range_deg[0]
        if kind is PanTiltAbsolute:
            pan = p.pan_to_counts(pan_deg)
            tilt = p.tilt_to_counts(tilt_deg)
        else:
            pan = round(
                check_degrees("pan_deg", pan_deg, (-pan_span, pan_span), p.name)
                * p.pan_counts_per_deg
            )
            tilt = round(
                check_degrees("tilt_deg", tilt_deg, (-tilt_span, tilt_span), p.name)
                * p.tilt_counts_per_deg
            )
        pan_code = p.pan_speed_code(speed, "speed")
        if tilt_speed is None and isinstance(speed, SpeedCode):
            # One pan speed code for both axes: tilt runs at its nearest (capped) code.
            tilt_code = min(pan_code, p.max_tilt_speed_code)
        else:
            tilt_code = p.tilt_speed_code(speed if tilt_speed is None else tilt_speed, "tilt_speed")
        # Worst case travel: the whole range (the start position is not known without asking).
        travel_s = max(
            pan_span / p.pan_speeds_deg_s[pan_code - 1],
            tilt_span / p.tilt_speeds_deg_s[tilt_code - 1],
        )
        timeout = travel_s * MOVE_TIMEOUT_FACTOR + self.move_timeout_margin_s
        return kind(pan_code, tilt_code, pan, tilt), timeout

    async def _wait_focus_settled(self, target: int) -> None:
        tolerance = self.profile.focus_settle_tolerance_counts
        last: int | None = None
        async with asyncio.timeout(FOCUS_SETTLE_TIMEOUT_S):
            while True:
                position = await self.focus_position()
                if abs(position - target) <= tolerance or position == last:
                    return
                last = position
                await asyncio.sleep(FOCUS_POLL_PERIOD_S)  # pacing: one inquiry per two fields

    async def _setup(self) -> Version:
        chain = await self._retry(self.link.ensure_addressed)
        if chain and self.address > chain:
            raise ViscaError(
                f"no camera at address {self.address}: Address Set found {chain} camera(s) on "
                f"{self.link.url}; check the configured address and the daisy-chain cabling"
            )
        await self._retry(lambda: self.link.inquire(self.address, IFClear()))
        power = await self._retry(lambda: self.link.inquire(self.address, PowerInquiry()))
        if not power.on:
            logger.info("camera %d is in standby: powering on", self.address)
            await self.power(on=True)
        version = await self.version()
        self.version_info = version
        self._adopt_profile(version)
        if version.max_sockets in (1, 2):
            self.link.set_max_sockets(self.address, version.max_sockets)
        await self.focus_mode(auto=False)
        logger.info(
            "camera %d (%s profile) ready: vendor %04X model %04X rom %04X, %d socket(s)",
            self.address, self.profile.name, version.vendor, version.model, version.rom,
            version.max_sockets,
        )  # fmt: skip
        return version

    def _adopt_profile(self, version: Version) -> None:
        """Use the profile of the model the camera identifies as; warn on a mismatch."""
        found = profile_for_version(version.vendor, version.model)
        if found is None:
            if self.adopt_profile:
                logger.warning(
                    "camera %d identifies as vendor 0x%04X model 0x%04X, which dffd has no profile "
                    "for; using the configured %s profile's limits — check that they hold for this "
                    "camera (known models: %s)",
                    self.address, version.vendor, version.model, self.profile.name,
                    ", ".join(p.name for p in PROFILES.values()),
                )  # fmt: skip
            return
        if found.key == self.profile.key:
            return  # the configured model (possibly a customised copy of its profile): keep it
        configured = self.profile
        if self.adopt_profile:
            self.profile = found
        logger.warning(
            "camera %d identifies as the %s (vendor 0x%04X model 0x%04X) but camera.model names "
            "the %s: %s; set camera.model = %r (the scheduler's speed tables and the focus range "
            "come from the configured model)",
            self.address, found.name, version.vendor, version.model, configured.name,
            f"using the {found.name}'s limits" if self.adopt_profile else "keeping the configured",
            found.key,
        )  # fmt: skip

    async def _reinit_step(self, link: LinkApi) -> None:
        # The same set-up, through the re-initialisation's pass of the link's gate.
        logger.info("re-initialising camera %d on %s", self.address, link.url)
        shadow = Camera(
            link,
            self.address,
            self.profile,
            retries=self.retries,
            move_timeout_margin_s=self.move_timeout_margin_s,
            adopt_profile=self.adopt_profile,
            completion_probe_s=self.completion_probe_s,
        )
        self.version_info = await shadow._setup()
        self.profile = shadow.profile


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _drive_axis(
    field: str,
    speed_deg_s: float,
    table: tuple[float, ...],
    model: str,
    directions: tuple[int, int, int],
) -> tuple[int, int]:
    positive, negative, stop = directions
    if (
        isinstance(speed_deg_s, bool)
        or not isinstance(speed_deg_s, int | float)
        or not math.isfinite(speed_deg_s)
    ):
        raise ValueError(f"{field} must be a finite signed speed in deg/s, got {speed_deg_s!r}")
    if abs(speed_deg_s) > table[-1]:
        raise ValueError(
            f"{field} = {speed_deg_s} deg/s is out of range [-{table[-1]}, {table[-1]}] deg/s "
            f"for the {model}"
        )
    if speed_deg_s == 0:
        return stop, 1  # speed 00 is a syntax error on some models: always send ≥ 01
    return (positive if speed_deg_s > 0 else negative), nearest_speed_code(abs(speed_deg_s), table)
