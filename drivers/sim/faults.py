"""Seeded fault injection for the simulated VISCA camera.

A :class:`Faults` object holds a parsed :class:`FaultSpec` and one seeded RNG. The device asks it,
byte by byte and packet by packet, whether to drop, corrupt, duplicate, delay or lose something, so
a run with the same seed and the same input is the same run. It also forwards the one-shot faults
(network change, power cycle, silence, port vanishing) to whatever transport it is bound to.

Fault-spec grammar (the ``--faults`` option of ``dffd sim-camera``)::

    SPEC  := "" | ITEM ("," ITEM)*          whitespace around items and around "=" is ignored
    ITEM  := KEY "=" VALUE

    seed=INT                  RNG seed (default 0)
    drop=P                    each byte is lost with probability P
    corrupt=P                 each byte has one random bit flipped with probability P
    duplicate=P               each byte is sent twice with probability P
    delay=P[:S]               each outgoing packet is held S s (default 0.05) with probability P;
                              the bytes behind it wait too (a stalled UART keeps order)
    lose_completion=P         each Completion is never sent with probability P
    garbage=P                 1–8 random bytes precede an outgoing packet with probability P
    network_change_every=S    an unsolicited Network Change (z0 38 FF) every S seconds
    power_cycle_every=S       the camera loses power every S seconds ...
    power_off=S               ... and stays dead S seconds (default 0.5), then powers up
    close_port_every=S        the server closes the pty every S seconds ...
    close_port_for=S          ... and reopens it S seconds later (default 1.0)
    direction=tx|rx|both      the stream drop/corrupt/duplicate apply to (default both)

``P`` is a probability in [0, 1]; ``S`` a positive number of seconds. Example:
``seed=3,drop=0.01,corrupt=0.01,duplicate=0.01,delay=0.02:0.05,lose_completion=0.05``.
"""

from __future__ import annotations

import dataclasses
import logging
import random
from dataclasses import dataclass
from typing import Literal, Protocol

logger = logging.getLogger(__name__)

Direction = Literal["tx", "rx", "both"]

DEFAULT_DELAY_S = 0.05  # a stall long enough to push a reply past a tight driver deadline
DEFAULT_POWER_OFF_S = 0.5  # dead time of a power cycle; long enough for a driver to notice
DEFAULT_CLOSE_PORT_FOR_S = 1.0  # how long an "unplugged" USB adapter stays away
GARBAGE_MAX_BYTES = 8  # longest burst of line noise inserted before a packet


class FaultSpecError(ValueError):
    """A ``--faults`` spec string could not be parsed; the message names the bad key."""


@dataclass(frozen=True, slots=True)
class FaultSpec:
    """What to inject, and how often (all zero/None: a clean camera)."""

    seed: int = 0
    drop: float = 0.0
    corrupt: float = 0.0
    duplicate: float = 0.0
    delay: float = 0.0
    delay_s: float = DEFAULT_DELAY_S
    lose_completion: float = 0.0
    garbage: float = 0.0
    network_change_every: float | None = None
    power_cycle_every: float | None = None
    power_off: float = DEFAULT_POWER_OFF_S
    close_port_every: float | None = None
    close_port_for: float = DEFAULT_CLOSE_PORT_FOR_S
    direction: Direction = "both"

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt", "duplicate", "delay", "lose_completion", "garbage"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise FaultSpecError(f"fault '{name}' must be a probability in [0, 1], got {value}")
        for name in ("delay_s", "power_off", "close_port_for"):
            if getattr(self, name) <= 0.0:
                raise FaultSpecError(f"fault '{name}' must be positive seconds")
        for name in ("network_change_every", "power_cycle_every", "close_port_every"):
            value = getattr(self, name)
            if value is not None and value <= 0.0:
                raise FaultSpecError(f"fault '{name}' must be positive seconds, got {value}")
        if self.direction not in ("tx", "rx", "both"):
            raise FaultSpecError(f"fault 'direction' must be tx, rx or both, got {self.direction}")

    @classmethod
    def parse(cls, spec: str) -> FaultSpec:
        """Parse a spec string (grammar in the module docstring); FaultSpecError names the key."""
        values: dict[str, object] = {}
        for raw_item in spec.split(","):
            item = raw_item.strip()
            if not item:
                continue
            key, sep, text = (part.strip() for part in item.partition("="))
            if not sep or not text:
                raise FaultSpecError(f"fault item {item!r} is not KEY=VALUE (e.g. drop=0.01)")
            if key not in _PARSERS:
                known = ", ".join(sorted(_PARSERS))
                raise FaultSpecError(f"unknown fault key {key!r}; known keys: {known}")
            try:
                values.update(_PARSERS[key](key, text))
            except ValueError as exc:
                if isinstance(exc, FaultSpecError):
                    raise
                raise FaultSpecError(f"fault {key!r}: bad value {text!r} ({exc})") from exc
        try:
            return cls(**values)  # type: ignore[arg-type]
        except FaultSpecError:
            raise
        except (TypeError, ValueError) as exc:
            raise FaultSpecError(f"fault spec {spec!r}: {exc}") from exc

    def __str__(self) -> str:
        """The spec string that parses back to this spec (only non-default keys)."""
        default = FaultSpec()
        items = [f"seed={self.seed}"]
        for field in dataclasses.fields(self):
            name = field.name
            value = getattr(self, name)
            if name in ("seed", "delay_s") or value == getattr(default, name):
                continue
            if name == "delay":
                items.append(f"delay={value}:{self.delay_s}")
            else:
                items.append(f"{name}={value}")
        return ",".join(items)

    @property
    def active(self) -> bool:
        """True if any fault is configured."""
        return dataclasses.replace(self, seed=0) != FaultSpec()


class FaultTarget(Protocol):
    """What the one-shot faults act on: the server (pty) or the in-process camera."""

    def inject_network_change(self) -> None: ...

    def power_cycle(self, off_s: float | None = None) -> None: ...

    def set_silent(self, silent: bool) -> None: ...

    def close_port(self) -> None: ...

    def reopen_port(self) -> None: ...


class Faults:
    """Seeded fault decisions for one simulated camera, plus one-shot faults for tests."""

    def __init__(self, spec: FaultSpec | str | None = None) -> None:
        if spec is None:
            spec = FaultSpec()
        elif isinstance(spec, str):
            spec = FaultSpec.parse(spec)
        self.spec = spec
        self.rng = random.Random(spec.seed)
        self._target: FaultTarget | None = None
        self.counts: dict[str, int] = dict.fromkeys(
            ("drop", "corrupt", "duplicate", "delay", "lose_completion", "garbage"), 0
        )

    # ---- stream decisions (called by the device) --------------------------------------------

    def mangle(self, data: bytes, direction: Literal["tx", "rx"]) -> bytes:
        """Apply byte-level drop/corrupt/duplicate to ``data`` travelling in ``direction``."""
        spec = self.spec
        if spec.direction not in (direction, "both") or not (
            spec.drop or spec.corrupt or spec.duplicate
        ):
            return data
        out = bytearray()
        for byte in data:
            if spec.drop and self.rng.random() < spec.drop:
                self.counts["drop"] += 1
                continue
            value = byte
            if spec.corrupt and self.rng.random() < spec.corrupt:
                value ^= 1 << self.rng.randrange(8)
                self.counts["corrupt"] += 1
            out.append(value)
            if spec.duplicate and self.rng.random() < spec.duplicate:
                out.append(value)
                self.counts["duplicate"] += 1
        if len(out) != len(data) or out != data:
            logger.debug("fault: %s %s -> %s", direction, data.hex(" "), out.hex(" "))
        return bytes(out)

    def stall_s(self) -> float:
        """Seconds to hold the next outgoing packet (0 for none)."""
        if self.spec.delay and self.rng.random() < self.spec.delay:
            self.counts["delay"] += 1
            return self.spec.delay_s
        return 0.0

    def lose_completion(self) -> bool:
        """True if this Completion should vanish."""
        if self.spec.lose_completion and self.rng.random() < self.spec.lose_completion:
            self.counts["lose_completion"] += 1
            return True
        return False

    def garbage(self) -> bytes:
        """Random line noise to put before the next outgoing packet (often empty)."""
        if self.spec.garbage and self.rng.random() < self.spec.garbage:
            self.counts["garbage"] += 1
            return self.rng.randbytes(self.rng.randint(1, GARBAGE_MAX_BYTES))
        return b""

    # ---- one-shot faults (called by tests; forwarded to the bound transport) ----------------

    def bind(self, target: FaultTarget | None) -> None:
        """Attach the transport that one-shot faults act on (done by the server)."""
        self._target = target

    def inject_network_change(self) -> None:
        """Send an unsolicited Network Change now."""
        self._bound().inject_network_change()

    def power_cycle(self, off_s: float | None = None) -> None:
        """Cut power now; the camera powers up ``off_s`` later (default ``power_off``)."""
        self._bound().power_cycle(off_s)

    def set_silent(self, silent: bool) -> None:
        """While silent the camera reads its input but never answers."""
        self._bound().set_silent(silent)

    def close_port(self) -> None:
        """Make the serial port vanish (USB adapter unplugged)."""
        self._bound().close_port()

    def reopen_port(self) -> None:
        """Bring the port back (re-plugged); the camera powers up and sends Network Change."""
        self._bound().reopen_port()

    def _bound(self) -> FaultTarget:
        if self._target is None:
            raise RuntimeError("Faults is not bound to a camera; pass it to SimCameraServer first")
        return self._target


# --------------------------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------------------------


def _probability(key: str, text: str) -> dict[str, object]:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise FaultSpecError(f"fault {key!r} must be a probability in [0, 1], got {text!r}")
    return {key: value}


def _seconds(key: str, text: str) -> dict[str, object]:
    value = float(text)
    if not value > 0.0:
        raise FaultSpecError(f"fault {key!r} must be positive seconds, got {text!r}")
    return {key: value}


def _seed(key: str, text: str) -> dict[str, object]:
    return {key: int(text, 0)}


def _delay(key: str, text: str) -> dict[str, object]:
    probability, _, seconds = text.partition(":")
    out = _probability(key, probability)
    if seconds:
        out["delay_s"] = _seconds(key, seconds)[key]
    return out


def _direction(key: str, text: str) -> dict[str, object]:
    if text not in ("tx", "rx", "both"):
        raise FaultSpecError(f"fault {key!r} must be tx, rx or both, got {text!r}")
    return {key: text}


_PARSERS = {
    "seed": _seed,
    "drop": _probability,
    "corrupt": _probability,
    "duplicate": _probability,
    "delay": _delay,
    "lose_completion": _probability,
    "garbage": _probability,
    "network_change_every": _seconds,
    "power_cycle_every": _seconds,
    "power_off": _seconds,
    "close_port_every": _seconds,
    "close_port_for": _seconds,
    "direction": _direction,
}
