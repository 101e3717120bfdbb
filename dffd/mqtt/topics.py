"""Topic names and their QoS/retain policy (docs/design.md §7): ``<prefix>/<camera>/<leaf>``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

TopicKind = Literal["estimate", "measurement", "status", "cmd", "cmd_reply", "sim_truth"]

# leaf below <prefix>/<camera>/, QoS, retained — the table of docs/design.md §7
TOPIC_POLICY: dict[TopicKind, tuple[str, int, bool]] = {
    "estimate": ("estimate", 0, False),
    "measurement": ("measurement", 0, False),
    "status": ("status", 1, True),
    "cmd": ("cmd", 1, False),
    "cmd_reply": ("cmd/reply", 1, False),
    "sim_truth": ("sim/truth", 0, False),
}


@dataclass(frozen=True, slots=True)
class Topics:
    """The concrete topic names of one camera."""

    prefix: str = "dffd"
    camera: str = "sim"

    @property
    def base(self) -> str:
        """``<prefix>/<camera>``."""
        return f"{self.prefix}/{self.camera}"

    def name(self, kind: TopicKind) -> str:
        """Full topic name of ``kind``."""
        return f"{self.base}/{TOPIC_POLICY[kind][0]}"

    @property
    def estimate(self) -> str:
        return self.name("estimate")

    @property
    def measurement(self) -> str:
        return self.name("measurement")

    @property
    def status(self) -> str:
        return self.name("status")

    @property
    def cmd(self) -> str:
        return self.name("cmd")

    @property
    def cmd_reply(self) -> str:
        return self.name("cmd_reply")

    @property
    def sim_truth(self) -> str:
        return self.name("sim_truth")


def qos(kind: TopicKind) -> int:
    """QoS level used for ``kind`` (docs/design.md §7)."""
    return TOPIC_POLICY[kind][1]


def retained(kind: TopicKind) -> bool:
    """Whether messages of ``kind`` are retained (only status)."""
    return TOPIC_POLICY[kind][2]
