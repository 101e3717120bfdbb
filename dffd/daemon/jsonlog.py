"""Durable local log: estimates and measurements as JSON lines in size-capped rotating files.

The MQTT backlog is bounded, so an outage longer than it can lose messages there; this log is
the record that loses nothing. :meth:`JsonlLog.append` only puts the payload on a bounded
queue (callable from the event loop or any thread, never touches the disk); a dedicated writer
thread serialises, writes, flushes after every batch, fsyncs at most once per
:data:`FSYNC_PERIOD_S` and rotates ``dffd.jsonl`` -> ``dffd.jsonl.1`` … ``.N`` like
``logging.handlers.RotatingFileHandler``. Each line is ``{"kind": "<estimate|measurement|…>",
<the payload's fields>}``; :func:`read_records` reads a directory back oldest first.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Self

from pydantic import BaseModel

__all__ = [
    "FSYNC_PERIOD_S",
    "STOP_TIMEOUT_S",
    "JsonlLog",
    "JsonlLogError",
    "JsonlLogStats",
    "read_records",
]

_LOGGER = logging.getLogger(__name__)

# fsync costs a disk round trip (ms on SSD, tens of ms on SD cards); once a second bounds what a
# power cut can take while keeping the writer thread mostly idle at 30 records/s.
FSYNC_PERIOD_S = 1.0
# Stop/flush: the queue holds at most queue_max short lines, written in well under a second
# on any disk that works; 5 s leaves systemd's TimeoutStopSec room.
STOP_TIMEOUT_S = 5.0
# Queue depth: at 30 fps (+ bursts) ~10 000 records is five minutes of a stalled disk.
DEFAULT_QUEUE_MAX = 10_000
_BATCH_MAX = 256  # records written between flushes when the queue is busy


class JsonlLogError(OSError):
    """The log directory cannot be used; the message says which and what to do."""


@dataclass(frozen=True, slots=True)
class JsonlLogStats:
    """Counters since start."""

    written: int  # records written to disk
    dropped: int  # records dropped because the queue was full or the disk failed
    rotations: int
    pending: int  # records queued, not yet written
    errors: int  # write/rotate failures


class _Flush:
    __slots__ = ("done",)

    def __init__(self) -> None:
        self.done = threading.Event()


class _Stop:
    __slots__ = ()


_STOP = _Stop()
_Record = tuple[str, BaseModel | Mapping[str, Any]]


class JsonlLog:
    """Rotating JSONL writer with its own thread; see the module docstring."""

    def __init__(
        self,
        directory: Path,
        *,
        max_bytes: int,
        backup_count: int,
        basename: str = "dffd",
        queue_max: int = DEFAULT_QUEUE_MAX,
    ) -> None:
        self.directory = Path(directory)
        self.path = self.directory / f"{basename}.jsonl"
        self.max_bytes = max_bytes
        self.backup_count = backup_count
        self._queue: queue.Queue[_Record | _Flush | _Stop] = queue.Queue(queue_max)
        self._thread: threading.Thread | None = None
        self._file: IO[bytes] | None = None
        self._size = 0
        self._last_fsync = 0.0
        self._lock = threading.Lock()  # guards the counters
        self._written = self._dropped = self._rotations = self._errors = 0

    # -- lifecycle --------------------------------------------------------------------------

    def start(self) -> None:
        """Create the directory, open the current file and start the writer thread."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            self._open()
        except OSError as exc:
            msg = (
                f"cannot write the log in {self.directory}: {exc.strerror or exc}; "
                "set log.dir to a writable directory (the service uses /var/lib/dffd)"
            )
            raise JsonlLogError(msg) from exc
        self._thread = threading.Thread(target=self._run, name="dffd-jsonlog", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> bool:
        """Write everything queued, fsync, close; True if the writer finished in time."""
        thread = self._thread
        if thread is None:
            return True
        self._put_control(_STOP, timeout_s)
        thread.join(timeout_s)
        self._thread = None
        if thread.is_alive():
            _LOGGER.error("JSONL log writer did not finish within %.1f s", timeout_s)
            return False
        return True

    async def aclose(self, timeout_s: float = STOP_TIMEOUT_S) -> bool:
        """:meth:`stop` without blocking the event loop."""
        return await asyncio.to_thread(self.stop, timeout_s)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- writing ----------------------------------------------------------------------------

    def append(self, kind: str, payload: BaseModel | Mapping[str, Any]) -> bool:
        """Queue one record (never blocks); False if it was dropped because the queue is full."""
        try:
            self._queue.put_nowait((kind, payload))
        except queue.Full:
            with self._lock:
                self._dropped += 1
            return False
        return True

    def flush(self, timeout_s: float = STOP_TIMEOUT_S) -> bool:
        """Block until every record queued before this call is written and flushed."""
        if self._thread is None:
            return self._queue.empty()
        marker = _Flush()
        if not self._put_control(marker, timeout_s):
            return False
        return marker.done.wait(timeout_s)

    def stats(self) -> JsonlLogStats:
        """A snapshot of the counters."""
        with self._lock:
            return JsonlLogStats(
                written=self._written,
                dropped=self._dropped,
                rotations=self._rotations,
                pending=self._queue.qsize(),
                errors=self._errors,
            )

    def files(self) -> list[Path]:
        """The log files, oldest first."""
        return _files(self.path)

    # -- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        stopping = False
        while not stopping:
            item = self._queue.get()
            batch = [item]
            while len(batch) < _BATCH_MAX:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            markers: list[_Flush] = []
            for entry in batch:
                if isinstance(entry, _Stop):
                    stopping = True
                elif isinstance(entry, _Flush):
                    markers.append(entry)
                else:
                    kind, payload = entry
                    try:
                        line = _line(kind, payload)
                    except (TypeError, ValueError) as exc:  # not JSON-serialisable: a caller bug
                        _LOGGER.error("JSONL log: cannot serialise a %r record: %s", kind, exc)
                        with self._lock:
                            self._dropped += 1
                        continue
                    self._write(line)
            self._sync(force=stopping or bool(markers))
            for marker in markers:
                marker.done.set()
        self._close()

    def _write(self, line: bytes) -> None:
        try:
            if self._file is None:
                self._open()
            if self._size and self._size + len(line) > self.max_bytes:
                self._rotate()
            assert self._file is not None
            self._file.write(line)
            self._size += len(line)
        except OSError as exc:
            with self._lock:
                self._dropped += 1
                self._errors += 1
                first = self._errors == 1
            (_LOGGER.error if first else _LOGGER.debug)(
                "JSONL log write to %s failed: %s; records are being dropped", self.path, exc
            )
            self._close()
            return
        with self._lock:
            self._written += 1

    def _sync(self, *, force: bool) -> None:
        if self._file is None:
            return
        try:
            self._file.flush()
            now = time.monotonic()
            if force or now - self._last_fsync >= FSYNC_PERIOD_S:
                os.fsync(self._file.fileno())
                self._last_fsync = now
        except OSError as exc:
            with self._lock:
                self._errors += 1
            _LOGGER.debug("JSONL log flush failed: %s", exc)

    def _open(self) -> None:
        self._file = self.path.open("ab")
        self._size = self._file.tell()

    def _close(self) -> None:
        if self._file is None:
            return
        try:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
        except OSError as exc:
            _LOGGER.debug("JSONL log close failed: %s", exc)
        self._file = None

    def _rotate(self) -> None:
        self._close()
        if self.backup_count > 0:
            for index in range(self.backup_count - 1, 0, -1):
                older = self.path.with_name(f"{self.path.name}.{index}")
                if older.exists():
                    older.replace(self.path.with_name(f"{self.path.name}.{index + 1}"))
            self.path.replace(self.path.with_name(f"{self.path.name}.1"))
        else:
            self.path.unlink(missing_ok=True)  # no backups wanted: start the file over
        with self._lock:
            self._rotations += 1
        self._open()

    def _put_control(self, item: _Flush | _Stop, timeout_s: float) -> bool:
        # Control items wait for room (they must not be dropped like data records).
        try:
            self._queue.put(item, timeout=timeout_s)
        except queue.Full:
            _LOGGER.error("JSONL log queue stayed full for %.1f s", timeout_s)
            return False
        return True


def read_records(directory: Path, basename: str = "dffd") -> Iterator[dict[str, Any]]:
    """Every record in ``directory``'s log files, oldest first (each with its ``kind``)."""
    for path in _files(Path(directory) / f"{basename}.jsonl"):
        with path.open("rb") as handle:
            for raw in handle:
                if raw.strip():
                    record: dict[str, Any] = json.loads(raw)
                    yield record


def _files(current: Path) -> list[Path]:
    backups = []
    for candidate in current.parent.glob(f"{current.name}.*"):
        suffix = candidate.name.rsplit(".", 1)[-1]
        if suffix.isdigit():
            backups.append((int(suffix), candidate))
    ordered = [path for _, path in sorted(backups, reverse=True)]
    if current.exists():
        ordered.append(current)
    return ordered


def _line(kind: str, payload: BaseModel | Mapping[str, Any]) -> bytes:
    if isinstance(payload, BaseModel):
        body = payload.model_dump_json(by_alias=True)
        # splice "kind" in front without re-parsing: body is a JSON object "{...}"
        head = json.dumps({"kind": kind})[:-1]
        return (head + ("," + body[1:] if body != "{}" else "}") + "\n").encode()
    return (json.dumps({"kind": kind, **payload}, separators=(",", ":")) + "\n").encode()
