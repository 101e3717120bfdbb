"""Recording format (docs/design.md §8): writer/reader round trip, inferred bursts, errors."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from dffd.core.synthetic import synthetic_lens
from dffd.core.types import FrameTag
from dffd.recording import (
    FrameRecord,
    PngEncoding,
    RecordingError,
    RecordingReader,
    RecordingWriter,
)
from drivers.frames import Frame

TAGS = [
    FrameTag("track", 10000, 1.5, -2.0),
    FrameTag("transit", None, 1.5, -2.0),
    FrameTag("burst", 9000, 1.5, -2.0, (0, 0)),
    FrameTag("burst", 10000, 1.5, -2.0, (0, 1)),
    FrameTag("burst", 11000, 1.5, -2.0, (0, 2)),
    FrameTag("track", 10000, 1.6, -2.1),
]


def _write(
    path: Path, truth: bool = True, bgr: bool = False, png: PngEncoding = "fast"
) -> list[Frame]:
    rng = np.random.default_rng(0)
    frames = []
    with RecordingWriter(path, 30, (64, 48), synthetic_lens().to_meta(), png=png) as w:
        for i, tag in enumerate(TAGS):
            shape = (48, 64, 3) if bgr else (48, 64)
            f = Frame(i, 100.0 + i / 30, rng.integers(0, 256, shape, dtype=np.uint8))
            w.write(f, tag, (4.0 + 0.01 * i, 0.1, -0.2) if truth else None)
            frames.append(f)
    return frames


@pytest.mark.parametrize(("bgr", "png"), [(False, "fast"), (True, "fast"), (False, "small")])
def test_round_trip_is_lossless(tmp_path: Path, bgr: bool, png: PngEncoding) -> None:
    frames = _write(tmp_path / "run", bgr=bgr, png=png)
    assert (tmp_path / "run/frames/000000.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rec = RecordingReader(tmp_path / "run")
    assert rec.fps == 30
    assert rec.frame_size == (64, 48)
    assert rec.meta["lens"]["focal_length_mm"] == 31.0
    got = list(rec)
    assert [t for _, t in got] == TAGS
    for (f, _), orig in zip(got, frames, strict=True):
        assert f.index == orig.index
        assert f.t == orig.t
        np.testing.assert_array_equal(f.image, orig.image)
    assert rec.truth is not None
    np.testing.assert_allclose(rec.truth.z_m, [4.0 + 0.01 * i for i in range(6)])
    assert rec.truth.x_m is not None
    assert rec.truth.z_at([100.0 + 0.5 / 30])[0] == pytest.approx(4.005)


def test_truth_carries_the_world_frame_3d_columns(tmp_path: Path) -> None:
    from dffd.recording import TRUTH_3D_COLUMNS, TRUTH_COLUMNS

    tag = FrameTag("track", 10000, 0.0, 0.0)
    image = np.zeros((48, 64), dtype=np.uint8)
    with RecordingWriter(tmp_path / "run", 30, (64, 48), synthetic_lens().to_meta()) as w:
        for i in range(3):
            row = (2.0, 0.1, -0.2, 0.5, 0.0, 2.0, 0.1 * i, 0.0, 0.0, 0.0, 0.0, -0.02, 0.2)
            w.write(Frame(i, i / 30, image), tag, row)
        with pytest.raises(RecordingError, match="13 values"):
            w.write(Frame(3, 0.1, image), tag, (2.0, 0.1, -0.2))
    header = (tmp_path / "run" / "truth.csv").read_text("utf-8").splitlines()[0]
    assert header.split(",") == ["t_s", *TRUTH_COLUMNS]
    truth = RecordingReader(tmp_path / "run").truth
    assert truth is not None
    assert set(truth.extra) == set(TRUTH_3D_COLUMNS)
    np.testing.assert_allclose(truth.extra["vx_world_m_s"], [0.0, 0.1, 0.2])
    np.testing.assert_allclose(truth.extra["angular_speed_rad_s"], [0.2] * 3)
    assert truth.x_m is not None


def test_frames_csv_has_the_design_columns_and_bursts_are_inferred(tmp_path: Path) -> None:
    _write(tmp_path / "run", truth=False)
    csv_path = tmp_path / "run" / "frames.csv"
    lines = csv_path.read_text().splitlines()
    assert lines[0].startswith("index,t_s,role,focus_counts,pan_deg,tilt_deg,file")
    assert lines[2].split(",")[3] == ""  # transit: empty focus_counts
    # strip the optional burst columns: ids are inferred from runs of burst frames
    csv_path.write_text("\n".join(",".join(ln.split(",")[:7]) for ln in lines) + "\n")
    rec = RecordingReader(tmp_path / "run")
    assert rec.truth is None
    assert [t.burst for t in (r.tag for r in rec.records)] == [
        None,
        None,
        (0, 0),
        (0, 1),
        (0, 2),
        None,
    ]


def test_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"meta\.json not found"):
        RecordingReader(tmp_path)
    _write(tmp_path / "run")
    with pytest.raises(RecordingError, match="already holds a recording"):
        RecordingWriter(tmp_path / "run", 30, (64, 48), {})
    meta = tmp_path / "run" / "meta.json"
    meta.write_bytes(b"\xff\xfe{}")
    with pytest.raises(RecordingError, match=r"cannot read .*meta\.json"):
        RecordingReader(tmp_path / "run")
    meta.write_text(json.dumps({"schema": 2}))
    with pytest.raises(RecordingError, match="schema"):
        RecordingReader(tmp_path / "run")
    meta.write_text(json.dumps({"schema": 1, "fps": 30, "frame_size": [64, 48], "lens": {}}))
    frames_csv = tmp_path / "run" / "frames.csv"
    frames_csv.write_text(frames_csv.read_text().replace("track", "tracking", 1))
    with pytest.raises(RecordingError, match="line 2"):
        RecordingReader(tmp_path / "run")


# -- read-ahead decoding ---------------------------------------------------------------------
class _CountingReader(RecordingReader):
    """Counts the frames whose decoding has started (from any thread)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.started = 0
        self._lock = threading.Lock()

    def load(self, rec: FrameRecord) -> Frame:
        with self._lock:
            self.started += 1
        return super().load(rec)


def _write_many(path: Path, n: int) -> list[Frame]:
    rng = np.random.default_rng(3)
    frames = []
    with RecordingWriter(path, 30, (64, 48), synthetic_lens().to_meta()) as w:
        for i in range(n):
            f = Frame(i, i / 30, rng.integers(0, 256, (48, 64), dtype=np.uint8))
            w.write(f, TAGS[i % 2])  # track / transit
            frames.append(f)
    return frames


def test_read_ahead_keeps_the_order_and_a_bounded_window(tmp_path: Path) -> None:
    frames = _write_many(tmp_path / "run", 60)
    reader = _CountingReader(tmp_path / "run")
    window = 4
    for k, (got, orig) in enumerate(
        zip(reader.frames(workers=3, window=window), frames, strict=True)
    ):
        assert got[0].index == orig.index
        np.testing.assert_array_equal(got[0].image, orig.image)
        # decoded or decoding: the frames handed out plus at most `window` ahead
        assert reader.started <= k + 1 + window
    assert reader.started == len(frames)
    sequential = [f.index for f, _ in reader.frames(workers=0)]
    assert sequential == list(range(60))


def test_read_ahead_raises_at_the_broken_frame_and_stops_its_threads(tmp_path: Path) -> None:
    _write_many(tmp_path / "run", 30)
    (tmp_path / "run" / "frames" / "000012.png").write_bytes(b"not a png")
    reader = RecordingReader(tmp_path / "run")
    it = reader.frames(workers=2, window=8)
    seen = [next(it)[0].index for _ in range(12)]
    with pytest.raises(RecordingError, match=r"000012\.png"):
        next(it)
    assert seen == list(range(12))
    # a consumer that stops early leaves no decoder behind either
    it = reader.frames(workers=2, window=8)
    next(it)
    it.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("dffd-decode")]
