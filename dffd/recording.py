"""Recordings (design.md §8): a directory of lossless PNG frames, their tags, and optional truth.

```
RUN/meta.json    {"schema": 1, "fps": 30, "frame_size": [w, h], "lens": {...}}
RUN/frames.csv   index,t_s,role,focus_counts,pan_deg,tilt_deg,file[,burst_id,burst_slot]
RUN/frames/      one PNG per frame
RUN/truth.csv    optional: t_s,z_m[,x_m,y_m[,x_world_m,…,angular_speed_rad_s]]
```
Truth frames (docs/design.md, recording section): ``z_m``, ``x_m``, ``y_m`` in the camera frame
at that instant; the 3D columns (:data:`TRUTH_3D_COLUMNS`) in the world frame of
docs/tracking3d.md.
``burst_id``/``burst_slot`` are optional trailing columns written by :class:`RecordingWriter`;
a recording without them (e.g. from another tool) gets burst ids inferred from runs of burst
frames (transit frames do not break a run, a track frame does).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self, cast

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.types import FrameRole, FrameTag
from drivers.frames import Frame

SCHEMA = 1
FRAME_COLUMNS = ("index", "t_s", "role", "focus_counts", "pan_deg", "tilt_deg", "file")
BURST_COLUMNS = ("burst_id", "burst_slot")
# truth.csv after t_s: depth and the camera-frame lateral offsets, then the 3D truth in the world
# frame (position, velocity, acceleration, turn rate about the upward vertical).
TRUTH_CAMERA_COLUMNS = ("z_m", "x_m", "y_m")
TRUTH_3D_COLUMNS = (
    "x_world_m", "y_world_m", "z_world_m",
    "vx_world_m_s", "vy_world_m_s", "vz_world_m_s",
    "ax_world_m_s2", "ay_world_m_s2", "az_world_m_s2",
    "angular_speed_rad_s",
)  # fmt: skip
TRUTH_COLUMNS = (*TRUTH_CAMERA_COLUMNS, *TRUTH_3D_COLUMNS)
_TRUTH_WIDTHS = (1, len(TRUTH_CAMERA_COLUMNS), len(TRUTH_COLUMNS))
_ROLES: frozenset[str] = frozenset({"track", "burst", "transit"})
# Frames decoded ahead of the consumer: a 640x480 gray frame is 0.3 MB (BGR 0.9 MB), so 16 hold
# at most ~15 MB; 16 keeps two decoders busy through the core's slowest frames (a 1-3 ms
# acquisition search against ~3 ms per PNG decode, measured on the 2-core dev machine).
PREFETCH_WINDOW = 16
# Decoding threads: PNG decoding is single-threaded in OpenCV, 0.3-2.5 ms per 640x480 frame.
MAX_DECODE_WORKERS = 4
PngEncoding = Literal["fast", "small"]
# How frames are written; both are lossless PNG that any reader opens. "fast": stored deflate
# blocks (zlib level 0) and no row filter — a 640x480 gray frame of the simulator is 301 KiB
# against 150 KiB, but decodes in 0.28 ms of CPU against 2.4 ms and encodes in 0.34 ms against
# 5.0 ms (OpenCV 5.0, one thread, the 2-core dev machine); replay is bound by decoding, so this is
# the default. "small": OpenCV's default encoding (zlib level 1 with adaptive filters).
PNG_PARAMS: dict[PngEncoding, tuple[int, ...]] = {
    "fast": (cv2.IMWRITE_PNG_COMPRESSION, 0)
    + (
        (cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE)
        if hasattr(cv2, "IMWRITE_PNG_FILTER")  # OpenCV >= 4.11; without it level 0 alone
        else ()
    ),
    "small": (),
}


def default_decode_workers() -> int:
    """Decoder threads for this machine: one per core, at most ``MAX_DECODE_WORKERS``."""
    return max(1, min(MAX_DECODE_WORKERS, os.cpu_count() or 1))


class RecordingError(Exception):
    """A recording is missing, malformed or cannot be written; the message says which file."""


@dataclass(frozen=True, slots=True)
class Truth:
    """Ground truth rows of ``truth.csv`` (x, y may be absent; ``extra``: every further column,
    e.g. the world-frame 3D truth of :data:`TRUTH_3D_COLUMNS`)."""

    t_s: npt.NDArray[np.float64]
    z_m: npt.NDArray[np.float64]
    x_m: npt.NDArray[np.float64] | None = None
    y_m: npt.NDArray[np.float64] | None = None
    extra: dict[str, npt.NDArray[np.float64]] = field(default_factory=dict)

    def z_at(self, t: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Depth interpolated at times ``t`` (NaN outside the truth's time span)."""
        tt = np.asarray(t, dtype=np.float64)
        return np.asarray(np.interp(tt, self.t_s, self.z_m, left=np.nan, right=np.nan))


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """One row of ``frames.csv``."""

    index: int
    t_s: float
    tag: FrameTag
    file: str


class RecordingWriter:
    """Write a recording, frames as lossless PNG (see :data:`PNG_PARAMS`); a context manager."""

    def __init__(
        self,
        path: str | Path,
        fps: float,
        frame_size: tuple[int, int],
        lens_meta: Mapping[str, Any],
        *,
        png: PngEncoding = "fast",
    ) -> None:
        self.path = Path(path)
        self._png_params = list(PNG_PARAMS[png])
        self._frames_dir = self.path / "frames"
        try:
            self._frames_dir.mkdir(parents=True, exist_ok=True)
            if (self.path / "frames.csv").exists():
                raise RecordingError(
                    f"{self.path} already holds a recording; choose a new directory"
                )
            meta = {
                "schema": SCHEMA,
                "fps": fps,
                "frame_size": [int(frame_size[0]), int(frame_size[1])],
                "lens": dict(lens_meta),
            }
            (self.path / "meta.json").write_text(json.dumps(meta, indent=2) + "\n", "utf-8")
            self._frames_file = (self.path / "frames.csv").open("w", newline="", encoding="utf-8")
        except OSError as exc:
            raise RecordingError(f"cannot create recording at {self.path}: {exc}") from exc
        self._frames = csv.writer(self._frames_file)
        self._frames.writerow([*FRAME_COLUMNS, *BURST_COLUMNS])
        self._truth_file: Any = None
        self._truth: Any = None
        self._truth_width: int | None = None
        self._closed = False

    def write(self, frame: Frame, tag: FrameTag, truth: Sequence[float] | None = None) -> None:
        """Append one frame; ``truth`` at ``frame.t`` is ``(z_m,)``, ``(z_m, x_m, y_m)`` or every
        column of :data:`TRUTH_COLUMNS` (camera frame, then the world-frame 3D truth)."""
        if self._closed:
            raise RecordingError(f"recording {self.path} is closed")
        name = f"{frame.index:06d}.png"
        if not cv2.imwrite(str(self._frames_dir / name), frame.image, self._png_params):
            raise RecordingError(f"cannot write frame {name} to {self._frames_dir}")
        burst = tag.burst if tag.burst is not None else ("", "")
        self._frames.writerow(
            [
                frame.index,
                repr(float(frame.t)),
                tag.role,
                "" if tag.focus_counts is None else tag.focus_counts,
                repr(float(tag.pan_deg)),
                repr(float(tag.tilt_deg)),
                f"frames/{name}",
                *burst,
            ]
        )
        if truth is not None:
            self._write_truth(frame.t, truth)

    def close(self) -> None:
        """Flush and close the files; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._frames_file.close()
        if self._truth_file is not None:
            self._truth_file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _write_truth(self, t: float, truth: Sequence[float]) -> None:
        width = len(truth)
        if width not in _TRUTH_WIDTHS:
            raise RecordingError(
                f"a truth row has {width} values; give {_TRUTH_WIDTHS} (columns {TRUTH_COLUMNS})"
            )
        if self._truth is None:
            self._truth_file = (self.path / "truth.csv").open("w", newline="", encoding="utf-8")
            self._truth = csv.writer(self._truth_file)
            self._truth.writerow(["t_s", *TRUTH_COLUMNS[:width]])
            self._truth_width = width
        if width != self._truth_width:
            raise RecordingError(
                f"truth rows must all have {self._truth_width} values, this one has {width}"
            )
        self._truth.writerow([repr(float(t)), *(repr(float(v)) for v in truth)])


class RecordingReader:
    """Read a recording: ``meta``, ``records``, ``truth``; iterate for ``(Frame, FrameTag)``."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        meta_path = self.path / "meta.json"
        try:
            meta = json.loads(meta_path.read_text("utf-8"))
        except FileNotFoundError as exc:
            raise RecordingError(f"{meta_path} not found: is {self.path} a recording?") from exc
        except (OSError, ValueError) as exc:  # ValueError: not JSON, or not UTF-8
            raise RecordingError(f"cannot read {meta_path}: {exc}") from exc
        if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
            raise RecordingError(f'{meta_path}: expected an object with "schema": {SCHEMA}')
        for key in ("fps", "frame_size", "lens"):
            if key not in meta:
                raise RecordingError(f'{meta_path}: missing "{key}"')
        self.meta: dict[str, Any] = meta
        self.records: list[FrameRecord] = _read_frames(self.path / "frames.csv")
        self.truth: Truth | None = _read_truth(self.path / "truth.csv")

    @property
    def fps(self) -> float:
        """Nominal frame rate."""
        return float(self.meta["fps"])

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height)."""
        w, h = self.meta["frame_size"]
        return int(w), int(h)

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[tuple[Frame, FrameTag]]:
        return self.frames()

    def frames(
        self, workers: int | None = None, window: int = PREFETCH_WINDOW
    ) -> Iterator[tuple[Frame, FrameTag]]:
        """``(Frame, FrameTag)`` in recording order, decoded by ``workers`` threads ahead.

        At most ``window`` frames are decoded and not yet consumed (memory stays bounded);
        ``workers=0`` decodes in the calling thread. A frame that cannot be read raises
        :class:`RecordingError` at its place in the order.
        """
        n_workers = default_decode_workers() if workers is None else workers
        if n_workers <= 0:
            for rec in self.records:
                yield self.load(rec), rec.tag
            return
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        pending: deque[tuple[Future[Frame], FrameTag]] = deque()
        records = iter(self.records)
        # cv2.imread releases the GIL while it decodes, so threads decode in parallel with the
        # consumer; the futures are collected in submission order.
        with ThreadPoolExecutor(n_workers, thread_name_prefix="dffd-decode") as pool:
            try:
                for rec in records:
                    pending.append((pool.submit(self.load, rec), rec.tag))
                    if len(pending) >= window:
                        break
                while pending:
                    future, tag = pending.popleft()
                    frame = future.result()
                    rec_next = next(records, None)
                    if rec_next is not None:
                        pending.append((pool.submit(self.load, rec_next), rec_next.tag))
                    yield frame, tag
            finally:  # consumer stopped early or a frame failed: drop the read-ahead
                for future, _ in pending:
                    future.cancel()

    def load(self, rec: FrameRecord) -> Frame:
        """Load the image of one record."""
        path = self.path / rec.file
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise RecordingError(f"cannot read frame image {path}")
        return Frame(rec.index, rec.t_s, np.asarray(image, dtype=np.uint8))


def _read_frames(path: Path) -> list[FrameRecord]:
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            fields = reader.fieldnames or []
            missing = [c for c in FRAME_COLUMNS if c not in fields]
            if missing:
                raise RecordingError(f"{path}: missing columns {', '.join(missing)}")
            has_burst = all(c in fields for c in BURST_COLUMNS)
            rows = list(reader)
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc}") from exc
    records: list[FrameRecord] = []
    inferred_id, slot, in_burst = -1, 0, False
    for n, row in enumerate(rows, start=2):
        try:
            role = row["role"]
            if role not in _ROLES:
                raise ValueError(f"role {role!r} is not track/burst/transit")
            counts = int(row["focus_counts"]) if row["focus_counts"].strip() else None
            burst: tuple[int, int] | None = None
            if role == "burst":
                if has_burst and row["burst_id"].strip():
                    burst = (int(row["burst_id"]), int(row["burst_slot"]))
                else:
                    if not in_burst:
                        inferred_id, slot, in_burst = inferred_id + 1, 0, True
                    burst = (inferred_id, slot)
                    slot += 1
            elif role == "track":
                in_burst = False
            t = float(row["t_s"])
            if not math.isfinite(t):
                raise ValueError("t_s is not finite")
            tag = FrameTag(
                role=cast(FrameRole, role),
                focus_counts=counts,
                pan_deg=float(row["pan_deg"]),
                tilt_deg=float(row["tilt_deg"]),
                burst=burst,
            )
            records.append(FrameRecord(int(row["index"]), t, tag, row["file"]))
        except (KeyError, ValueError) as exc:
            raise RecordingError(f"{path} line {n}: {exc}") from exc
    return records


def _read_truth(path: Path) -> Truth | None:
    if not path.exists():
        return None
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            fields = reader.fieldnames or []
            if "t_s" not in fields or "z_m" not in fields:
                raise RecordingError(f"{path}: needs columns t_s,z_m[,x_m,y_m]")
            rows = list(reader)
        t = np.array([float(r["t_s"]) for r in rows])
        z = np.array([float(r["z_m"]) for r in rows])
        x = np.array([float(r["x_m"]) for r in rows]) if "x_m" in fields else None
        y = np.array([float(r["y_m"]) for r in rows]) if "y_m" in fields else None
        known = {"t_s", "z_m", "x_m", "y_m"}
        extra = {
            name: np.array([float(r[name]) for r in rows]) for name in fields if name not in known
        }
    except (OSError, ValueError, KeyError) as exc:
        raise RecordingError(f"cannot read {path}: {exc}") from exc
    if len(t) > 1 and np.any(np.diff(t) < 0):
        raise RecordingError(f"{path}: t_s must be non-decreasing")
    return Truth(t, z, x, y, extra)
