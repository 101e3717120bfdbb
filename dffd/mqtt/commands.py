"""The ``…/cmd`` path: one command's JSON parsed, validated, run by the handler and answered.

docs/design.md §7. :func:`execute_command` never raises: a payload that is not a JSON object, an
unknown command, a bad field, a handler that refuses (:class:`CommandRejected`), overruns
:data:`COMMAND_TIMEOUT_S` or fails becomes an ``ok: false`` :class:`~dffd.mqtt.models.CommandReply`
with a clear error. ``ping`` is answered here; every other command goes to the handler. The
:class:`~dffd.mqtt.publisher.Publisher` runs it for each message on ``…/cmd`` and for the web
dashboard (:meth:`~dffd.mqtt.publisher.Publisher.execute`).
"""

from __future__ import annotations

import asyncio
import inspect
import json
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

from pydantic import ValidationError

from dffd.mqtt.models import (
    COMMAND_ADAPTER,
    COMMAND_NAMES,
    Command,
    CommandReply,
    Ping,
    wall_time,
)

__all__ = [
    "COMMAND_TIMEOUT_S",
    "CommandHandler",
    "CommandRejected",
    "CommandResult",
    "execute_command",
]

_LOGGER = logging.getLogger(__name__)

# A command handler (acquire, home…) only queues work for the scheduler; 5 s is generous.
COMMAND_TIMEOUT_S = 5.0

CommandResult = dict[str, Any] | None
# A handler returns the reply's ``result`` (or None), sync or async; CommandRejected refuses.
CommandHandler = Callable[[Command], Awaitable[CommandResult] | CommandResult]


class CommandRejected(Exception):  # noqa: N818 - it is an outcome, not a crash
    """Raised by a command handler: the command is refused; the message goes into the reply."""


async def execute_command(
    payload: object, on_command: CommandHandler | None, version: str
) -> CommandReply:
    """Parse, validate and run one command; every failure becomes an ``ok: false`` reply."""
    command_id: str | int | None = None
    name: str | None = None

    def reply(
        *, ok: bool, error: str | None = None, result: dict[str, Any] | None = None
    ) -> CommandReply:
        return CommandReply(
            id=command_id, cmd=name, ok=ok, error=error, result=result, t=wall_time()
        )

    try:
        data = json.loads(payload if isinstance(payload, bytes | bytearray | str) else b"")
    except (ValueError, RecursionError) as exc:
        # RecursionError: nesting deeper than the interpreter's limit (e.g. b"[" * 10**5);
        # uncaught, it would end the command loop and with it the MQTT client.
        return reply(
            ok=False,
            error=f'payload is not JSON ({exc}); send an object such as {{"cmd": "ping", "id": 1}}',
        )
    if not isinstance(data, dict):
        return reply(ok=False, error='payload must be a JSON object with a "cmd" key')
    raw_id = data.get("id")
    if (isinstance(raw_id, str) and len(raw_id) <= 128) or (
        isinstance(raw_id, int) and not isinstance(raw_id, bool)
    ):
        command_id = raw_id
    if isinstance(data.get("cmd"), str):
        name = data["cmd"]
    try:
        command = COMMAND_ADAPTER.validate_python(data)
    except ValidationError as exc:
        return reply(ok=False, error=_describe_command_error(exc, data))
    if isinstance(command, Ping):
        return reply(ok=True, result={"t_mono": time.monotonic(), "version": version})
    if on_command is None:
        return reply(ok=False, error=f"this process does not execute {name!r} commands")
    try:
        async with asyncio.timeout(COMMAND_TIMEOUT_S):
            outcome = on_command(command)
            result = await outcome if inspect.isawaitable(outcome) else outcome
    except CommandRejected as exc:
        return reply(ok=False, error=str(exc))
    except TimeoutError:
        return reply(ok=False, error=f"{name!r} timed out after {COMMAND_TIMEOUT_S:.0f} s; retry")
    except Exception as exc:  # a handler bug must not take the client down
        _LOGGER.exception("command %r failed", name)
        return reply(ok=False, error=f"internal error in {name!r} ({type(exc).__name__}: {exc})")
    return reply(ok=True, result=result)


def _describe_command_error(exc: ValidationError, data: dict[str, Any]) -> str:
    problems = []
    for error in exc.errors(include_url=False):
        kind = error["type"]
        if kind == "union_tag_not_found":
            return f'missing "cmd"; use one of {", ".join(COMMAND_NAMES)}'
        if kind == "union_tag_invalid":
            return f"unknown command {data.get('cmd')!r}; use one of {', '.join(COMMAND_NAMES)}"
        field = ".".join(str(part) for part in error["loc"][1:]) or "(command)"
        if kind == "extra_forbidden":
            problems.append(f"{field}: unknown field for {data.get('cmd')!r}")
        elif kind == "missing":
            problems.append(f"{field}: required")
        else:
            problems.append(f"{field}: {error['msg']} (got {error.get('input')!r})")
    return "; ".join(problems)
