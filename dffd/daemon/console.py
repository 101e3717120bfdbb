"""Live console view of the running daemon (rich), or plain periodic log lines without a TTY.

The daemon hands a :class:`ConsoleSnapshot` to :meth:`Console.update` once per status period;
nothing here touches the camera, the estimator or MQTT.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

from rich.console import Console as RichConsole
from rich.console import Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

_LOGGER = logging.getLogger(__name__)

# Screen refreshes per second of the live view: enough for a human, cheap for the loop.
REFRESH_PER_S = 4.0
# An estimate older than this is shown as stale, not as the current depth: estimates come at
# 10–30 Hz while tracking, so a second without one means tracking has stopped.
STALE_AFTER_S = 1.0


@dataclass(frozen=True, slots=True)
class ConsoleSnapshot:
    """What the view shows at one instant."""

    camera: str
    state: str
    uptime_s: float
    frame_hz: float
    estimate_hz: float
    depth_hz: float
    depth_limit_hz: float | None
    link_connected: bool
    link_timeouts: int
    link_errors: int
    link_reconnects: int
    mqtt_connected: bool
    mqtt_backlog: int
    frames_dropped: int
    bursts_accepted: int
    bursts_rejected: int
    roles: dict[str, int] = field(default_factory=dict)
    depth_m: dict[str, float | None] = field(default_factory=dict)
    last_estimate_age_s: float | None = None  # None: no estimate since start or release
    best: str = "lpv"
    truth_z_m: float | None = None
    size_m: float | None = None
    pan_deg: float = 0.0
    tilt_deg: float = 0.0


class Console:
    """A rich Live panel when ``live`` (stdout is a TTY), else one INFO log line per update."""

    def __init__(self, *, live: bool) -> None:
        self.live = live
        self._live: Live | None = None

    def __enter__(self) -> Self:
        if self.live:
            self._live = Live(
                Text("dffd starting…"),
                console=RichConsole(),
                refresh_per_second=REFRESH_PER_S,
                transient=False,
            )
            self._live.__enter__()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._live is not None:
            self._live.__exit__(exc_type, exc, tb)
            self._live = None

    def update(self, snap: ConsoleSnapshot) -> None:
        """Show ``snap``."""
        if self._live is not None:
            self._live.update(render(snap))
            return
        best = _num(snap.depth_m.get(snap.best), 3)
        if is_stale(snap):
            best = f"{best} ({_age(snap.last_estimate_age_s)})"
        _LOGGER.info(
            "%s %s: %.1f fps, %.1f est/s, depth %.2f/%s Hz; z[%s]=%s truth=%s; link %s "
            "(timeouts %d), mqtt %s (backlog %d), dropped %d",
            snap.camera, snap.state, snap.frame_hz, snap.estimate_hz, snap.depth_hz,
            _num(snap.depth_limit_hz, 2), snap.best, best, _num(snap.truth_z_m, 3),
            "up" if snap.link_connected else "DOWN", snap.link_timeouts,
            "up" if snap.mqtt_connected else "DOWN", snap.mqtt_backlog, snap.frames_dropped,
        )  # fmt: skip


def is_stale(snap: ConsoleSnapshot) -> bool:
    """True when the depths in ``snap`` are not current (none, old, or not tracking)."""
    age = snap.last_estimate_age_s
    return age is None or age > STALE_AFTER_S or snap.state != "tracking"


def render(snap: ConsoleSnapshot) -> Group:
    """The live view of ``snap`` as rich renderables."""
    head = Text.assemble(
        ("dffd ", "bold"),
        (snap.camera, "bold cyan"),
        "  state ",
        (snap.state, "bold green" if snap.state == "tracking" else "bold yellow"),
        f"  up {snap.uptime_s:.0f} s  pan {snap.pan_deg:+.1f}°  tilt {snap.tilt_deg:+.1f}°",
    )
    rates = Table(title="rates", expand=False)
    for col in ("frames/s", "estimates/s", "depth/s", "limit/s", "ratio"):
        rates.add_column(col, justify="right")
    limit = snap.depth_limit_hz
    ratio = snap.depth_hz / limit if limit else None
    rates.add_row(
        f"{snap.frame_hz:.1f}", f"{snap.estimate_hz:.1f}", f"{snap.depth_hz:.2f}",
        _num(limit, 2), _num(ratio, 2),
    )  # fmt: skip
    stale = is_stale(snap)
    title = "depth (m)"
    if stale:
        title += f" — last estimate {_age(snap.last_estimate_age_s)}, not current"
    depth = Table(title=title, expand=False, style="dim" if stale else "")
    depth.add_column("estimator")
    depth.add_column("z", justify="right")
    depth.add_column("error vs truth", justify="right")
    for name, z in snap.depth_m.items():
        err = None if z is None or snap.truth_z_m is None else z - snap.truth_z_m
        label = f"{name} (best)" if name == snap.best else name
        depth.add_row(label, _num(z, 3), _num(err, 3), style="dim strike" if stale else "")
    depth.add_row("truth", _num(snap.truth_z_m, 3), "")
    health = Table(title="health", expand=False)
    for col in ("VISCA link", "timeouts", "errors", "reconnects", "MQTT", "backlog", "dropped"):
        health.add_column(col, justify="right")
    health.add_row(
        "up" if snap.link_connected else "[red]DOWN[/red]",
        str(snap.link_timeouts), str(snap.link_errors), str(snap.link_reconnects),
        "up" if snap.mqtt_connected else "[red]DOWN[/red]",
        str(snap.mqtt_backlog), str(snap.frames_dropped),
    )  # fmt: skip
    roles = ", ".join(f"{k} {v}" for k, v in snap.roles.items())
    foot = Text(
        f"bursts accepted {snap.bursts_accepted}, rejected {snap.bursts_rejected};"
        f" frames {roles}; size R̂ = {_num(snap.size_m, 4)} m   (Ctrl-C to stop)"
    )
    return Group(head, rates, depth, health, foot)


def _age(age_s: float | None) -> str:
    return "none since start or release" if age_s is None else f"{age_s:.1f} s ago"


def _num(value: float | None, digits: int) -> str:
    if value is None or not math.isfinite(value):
        return "–"
    return f"{value:.{digits}f}"
