"""Live console view of the running daemon (rich), or plain periodic log lines without a TTY.

The daemon hands a :class:`ConsoleSnapshot` to :meth:`Console.update` once per status period;
nothing here touches the camera, the estimator or MQTT. While the live view is up, log records
are printed through it (above the view): a handler writing to the terminal behind rich's back
would leave fragments of old views stuck on the screen. :meth:`Console.farewell` says how the
run ended, after the view is gone.
"""

from __future__ import annotations

import logging
import math
import sys
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

from rich import box
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
# What the cf1 row says when it has no depth because no target size is known (CF1 needs R).
CF1_NEEDS_SIZE = "needs target.known_size_m"


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
    known_size_m: float | None = None  # the size CF1 is told (None: CF1 has no depth)
    measured_age_s: float | None = None  # age of depth_m["measured"] (a burst's, not per frame)
    search: str | None = None  # the search sweep, in a few words (None: not sweeping)


class Console:
    """A rich Live panel when ``live`` (stdout is a TTY), else one INFO log line per update."""

    def __init__(self, *, live: bool, terminal: RichConsole | None = None) -> None:
        self.live = live
        self._live: Live | None = None
        self._terminal = terminal  # the rich console to draw on (default: stdout)
        self._rich: RichConsole | None = None
        self._swapped: list[tuple[logging.Handler, logging.Handler]] = []

    def __enter__(self) -> Self:
        if self.live:
            self._rich = self._terminal or RichConsole()
            # Before Live swaps sys.stdout/stderr for its proxies: what the handlers write to.
            streams = (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__)
            self._live = Live(
                Text("dffd starting: camera, broker, estimator…"),
                console=self._rich,
                refresh_per_second=REFRESH_PER_S,
                transient=False,
            )
            self._live.__enter__()
            self._route_logging(self._rich, {id(stream) for stream in streams})
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
        self._restore_logging()

    def farewell(self, message: str) -> None:
        """Say how the run ended: printed below the last view when live, else logged."""
        if self._rich is not None:
            self._rich.print(Text(message, style="bold"))
        else:
            _LOGGER.info("%s", message)

    def _route_logging(self, console: RichConsole, terminal: set[int]) -> None:
        """Send the root logger's handlers writing to the ``terminal`` streams (ids) through
        ``console`` while the view is up."""
        root = logging.getLogger()
        for handler in list(root.handlers):
            if type(handler) is not logging.StreamHandler or id(handler.stream) not in terminal:
                continue  # files, journald, pytest's capture: not the terminal
            replacement = _ConsoleLogHandler(console)
            replacement.setLevel(handler.level)
            replacement.setFormatter(handler.formatter)
            for log_filter in handler.filters:
                replacement.addFilter(log_filter)
            root.removeHandler(handler)
            root.addHandler(replacement)
            self._swapped.append((handler, replacement))

    def _restore_logging(self) -> None:
        root = logging.getLogger()
        for original, replacement in self._swapped:
            root.removeHandler(replacement)
            root.addHandler(original)
        self._swapped.clear()

    def update(self, snap: ConsoleSnapshot) -> None:
        """Show ``snap``."""
        if self._live is not None:
            self._live.update(render(snap))
            return
        best = f"{_num(snap.depth_m.get(snap.best), 3)} ({_age(snap.last_estimate_age_s)})"
        if is_stale(snap):
            best += " not current"
        state = snap.state if not snap.search else f"{snap.state} ({snap.search})"
        _LOGGER.info(
            "%s %s: %.1f fps, %.1f est/s, depth %.2f/%s Hz; z[%s]=%s truth=%s; link %s "
            "(timeouts %d), mqtt %s (backlog %d), dropped %d",
            snap.camera, state, snap.frame_hz, snap.estimate_hz, snap.depth_hz,
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
    stale = is_stale(snap)
    head = Text.assemble(
        ("dffd ", "bold"),
        (snap.camera, "bold cyan"),
        " ",
        (snap.state, "bold green" if snap.state == "tracking" else "bold yellow"),
        (f" ({snap.search})" if snap.search else "", "yellow"),
        " · last estimate ",
        (_age(snap.last_estimate_age_s), "bold red" if stale else ""),
        f" · up {snap.uptime_s:.0f} s · pan {snap.pan_deg:+.1f}° tilt {snap.tilt_deg:+.1f}°",
    )
    # Compact tables (no outer border): the whole view fits an 80×24 terminal.
    rates = Table(box=box.SIMPLE_HEAD, show_edge=False, expand=False, pad_edge=False)
    for col in ("frames/s", "estimates/s", "depth/s", "limit/s", "ratio"):
        rates.add_column(col, justify="right")
    limit = snap.depth_limit_hz
    ratio = snap.depth_hz / limit if limit else None
    rates.add_row(
        f"{snap.frame_hz:.1f}", f"{snap.estimate_hz:.1f}", f"{snap.depth_hz:.2f}",
        _num(limit, 2), _num(ratio, 2),
    )  # fmt: skip
    title = "depth (m)"
    if stale:
        title += f" — last estimate {_age(snap.last_estimate_age_s)}, not current"
    depth = Table(
        title=title, title_justify="left", box=box.SIMPLE_HEAD, show_edge=False,
        expand=False, pad_edge=False, style="dim" if stale else "",
    )  # fmt: skip
    depth.add_column("estimator")
    depth.add_column("z", justify="right")
    depth.add_column("error vs truth", justify="right")
    for name, z in snap.depth_m.items():
        err = None if z is None or snap.truth_z_m is None else z - snap.truth_z_m
        label = f"{name} (best)" if name == snap.best else name
        if name == "measured" and snap.measured_age_s is not None:
            label = f"measured ({snap.measured_age_s:.1f} s ago)"
        if name == "cf1" and z is None and snap.known_size_m is None:
            depth.add_row(label, "–", CF1_NEEDS_SIZE, style="dim")
            continue
        depth.add_row(label, _num(z, 3), _num(err, 3), style="dim strike" if stale else "")
    depth.add_row("truth", _num(snap.truth_z_m, 3), "")
    health = Table(box=box.SIMPLE_HEAD, show_edge=False, expand=False, pad_edge=False)
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
    gap = Text("")
    return Group(head, gap, rates, gap, depth, gap, health, foot)


class _ConsoleLogHandler(logging.Handler):
    """Prints log records through the live view's console (rich keeps the view below them)."""

    def __init__(self, console: RichConsole) -> None:
        super().__init__()
        self.console = console

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.print(Text(self.format(record)), soft_wrap=True)
        except Exception:  # noqa: BLE001 - logging must never raise (logging.Handler's contract)
            self.handleError(record)


def _age(age_s: float | None) -> str:
    return "none since start or release" if age_s is None else f"{age_s:.1f} s ago"


def _num(value: float | None, digits: int) -> str:
    if value is None or not math.isfinite(value):
        return "–"
    return f"{value:.{digits}f}"
