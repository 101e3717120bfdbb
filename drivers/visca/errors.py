"""Exceptions of the VISCA driver: one root, subclasses that carry what went wrong.

Every exception says what happened and what to do about it; error replies carry the VISCA code
and the socket so callers can branch on them (``except ViscaNotExecutableError``) or on the data
(``exc.code``).
"""

from __future__ import annotations

from drivers.visca.codec_replies import ErrorCode


class ViscaError(Exception):
    """Root of every error raised by the VISCA link and camera API."""


class ViscaErrorReply(ViscaError):  # noqa: N818 - the name the design gives it
    """The camera answered a request with an error packet ``z0 6y EE FF``."""

    hint = "check the command and the camera's state"

    def __init__(
        self, code: int, socket: int, address: int = 0, request: str = "", hint: str = ""
    ) -> None:
        self.code = code
        self.socket = socket
        self.address = address
        self.request = request
        self.context_hint = hint  # the caller's better-informed hint (replaces the class's)
        where = f"camera {address}" if address else "camera"
        what = f" to {request}" if request else ""
        super().__init__(
            f"{where} replied error 0x{code:02X} ({ErrorCode.describe(code)}) in socket {socket}"
            f"{what}: {hint or self.hint}"
        )

    def with_hint(self, hint: str) -> ViscaErrorReply:
        """The same error (same class and data) with ``hint`` as its advice."""
        return type(self)(self.code, self.socket, self.address, self.request, hint)

    def __reduce__(self) -> tuple[type[ViscaErrorReply], tuple[int, int, int, str, str]]:
        return (
            type(self),
            (self.code, self.socket, self.address, self.request, self.context_hint),
        )


class ViscaMessageLengthError(ViscaErrorReply):
    """Error 01: the packet was too long or too short for the camera."""

    hint = (
        "the camera rejected the packet's length; the driver frames every packet as the VISCA "
        "spec gives it, so a device that does not implement this command (firmware, or a model "
        "other than camera.model) is the likely cause — if the camera's manual lists this command "
        "with these bytes, report it with the DEBUG log"
    )


class ViscaSyntaxError(ViscaErrorReply):
    """Error 02: the camera does not understand the command (or an argument is out of range)."""

    hint = (
        "the camera does not accept this command or one of its values: check that camera.model "
        "names this camera (its version inquiry identifies it) and that its firmware supports "
        "the command"
    )


class ViscaBufferFullError(ViscaErrorReply):
    """Error 03: both command sockets were busy (the link retried and gave up)."""

    hint = "another controller may share the port; wait for running moves to finish"


class ViscaCancelledError(ViscaErrorReply):
    """Error 04: the command was cancelled (by a Cancel or a Stop)."""

    hint = "the command was cancelled on request; nothing to fix"


class ViscaNoSocketError(ViscaErrorReply):
    """Error 05: a Cancel named a socket with no command in it."""

    hint = "the command had already finished"


class ViscaNotExecutableError(ViscaErrorReply):
    """Error 41: the command cannot run in the camera's current state."""

    hint = (
        "the camera's mode forbids it (e.g. manual focus commands while autofocus is on: "
        "switch to manual focus first; or the camera is in standby: power it on)"
    )


ERROR_CLASSES: dict[int, type[ViscaErrorReply]] = {
    ErrorCode.MESSAGE_LENGTH: ViscaMessageLengthError,
    ErrorCode.SYNTAX: ViscaSyntaxError,
    ErrorCode.BUFFER_FULL: ViscaBufferFullError,
    ErrorCode.CANCELLED: ViscaCancelledError,
    ErrorCode.NO_SOCKET: ViscaNoSocketError,
    ErrorCode.NOT_EXECUTABLE: ViscaNotExecutableError,
}


def error_from_reply(
    code: int, socket: int, address: int = 0, request: str = ""
) -> ViscaErrorReply:
    """Build the typed exception for an error reply (``ViscaErrorReply`` for unknown codes)."""
    return ERROR_CLASSES.get(code, ViscaErrorReply)(code, socket, address, request)


class ViscaTimeoutError(ViscaError, TimeoutError):
    """A named wait expired (``wait`` is e.g. ``"ACK"``, ``"Completion"``, ``"inquiry reply"``)."""

    def __init__(self, wait: str, timeout_s: float, request: str = "", address: int = 0) -> None:
        self.wait = wait
        self.timeout_s = timeout_s
        self.request = request
        self.address = address
        where = f" from camera {address}" if address else ""
        what = f" to {request}" if request else ""
        super().__init__(
            f"no {wait}{where}{what} within {timeout_s:.3g} s: check the cable, the camera's "
            "power and address, and the baud rate (9600 unless the camera is set otherwise)"
        )

    def __reduce__(self) -> tuple[type[ViscaTimeoutError], tuple[str, float, str, int]]:
        return (type(self), (self.wait, self.timeout_s, self.request, self.address))


class LinkDownError(ViscaError):
    """The serial port is closed or vanished (adapter unplugged); the link is reconnecting."""


class ViscaNetworkChangeError(ViscaError):
    """The camera chain reported a Network Change (power cycle, re-cabling) mid-request."""


class LinkBusyError(ViscaError):
    """Too many requests are queued for one camera; the caller is issuing faster than it runs."""
