"""Durable JSONL log: rotation, nothing lost, flush, bounded queue, unusable directory."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from dffd.daemon.jsonlog import JsonlLog, JsonlLogError, read_records
from dffd.mqtt.models import DepthByEstimator, Estimate


def _estimate(seq: int) -> Estimate:
    return Estimate(
        seq=seq,
        t=1.7e9 + seq,
        t_mono=float(seq),
        state="tracking",
        depth_m=DepthByEstimator(measured=None, cf1=None, cf2=2.0, lpv=2.0, kf=2.0),
        best="lpv",
        z_m=2.0,
        sigma_m=0.03,
        size_m=0.036,
        r_px=40.0,
        position_m=(0.0, 0.0, 2.0),
        pan_deg=0.0,
        tilt_deg=0.0,
    )


def test_rotation_keeps_every_record_in_order(tmp_path: Path) -> None:
    n = 2000
    with JsonlLog(tmp_path / "log", max_bytes=16_384, backup_count=100) as log:
        for seq in range(n):
            assert log.append("estimate", _estimate(seq))
            if seq % 7 == 0:
                log.append("measurement", {"seq": seq, "z_m": 2.0})
    stats = log.stats()
    assert stats.dropped == 0
    assert stats.errors == 0
    assert stats.rotations >= 10
    files = log.files()
    assert len(files) == stats.rotations + 1
    assert all(path.stat().st_size <= 16_384 for path in files)
    records = list(read_records(tmp_path / "log"))
    estimates = [r for r in records if r["kind"] == "estimate"]
    assert [r["seq"] for r in estimates] == list(range(n))
    assert estimates[0]["schema"] == 1
    assert estimates[0]["z_m"] == 2.0
    assert Estimate.model_validate({k: v for k, v in estimates[5].items() if k != "kind"})
    assert sum(r["kind"] == "measurement" for r in records) == len(range(0, n, 7))
    assert stats.written == len(records)


def test_backup_count_caps_the_number_of_files(tmp_path: Path) -> None:
    with JsonlLog(tmp_path, max_bytes=4096, backup_count=3) as log:
        for seq in range(500):
            log.append("estimate", _estimate(seq))
    names = sorted(p.name for p in log.files())
    assert names == ["dffd.jsonl", "dffd.jsonl.1", "dffd.jsonl.2", "dffd.jsonl.3"]
    kept = [r["seq"] for r in read_records(tmp_path)]
    assert kept == list(range(500 - len(kept), 500))  # the newest, contiguous


def test_flush_makes_records_readable_while_running(tmp_path: Path) -> None:
    log = JsonlLog(tmp_path, max_bytes=1 << 20, backup_count=1)
    log.start()
    try:
        for seq in range(10):
            log.append("estimate", _estimate(seq))
        assert log.flush()
        lines = (tmp_path / "dffd.jsonl").read_text().splitlines()
        assert [json.loads(line)["seq"] for line in lines] == list(range(10))
    finally:
        assert log.stop()


def test_appends_from_many_threads_are_all_written(tmp_path: Path) -> None:
    log = JsonlLog(tmp_path, max_bytes=8192, backup_count=1000)
    log.start()

    def produce(offset: int) -> None:
        for i in range(300):
            log.append("measurement", {"seq": offset + i})

    threads = [threading.Thread(target=produce, args=(k * 1000,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert log.stop()
    seqs = sorted(r["seq"] for r in read_records(tmp_path))
    assert seqs == sorted(k * 1000 + i for k in range(4) for i in range(300))


def test_full_queue_drops_and_counts_instead_of_blocking(tmp_path: Path) -> None:
    log = JsonlLog(tmp_path, max_bytes=1 << 20, backup_count=1, queue_max=5)
    # writer not started: nothing drains the queue
    accepted = [log.append("estimate", {"seq": i}) for i in range(8)]
    assert accepted == [True] * 5 + [False] * 3
    assert log.stats().dropped == 3
    log.start()
    assert log.stop()
    assert [r["seq"] for r in read_records(tmp_path)] == [0, 1, 2, 3, 4]


def test_unserialisable_record_is_dropped_not_fatal(tmp_path: Path) -> None:
    with JsonlLog(tmp_path, max_bytes=1 << 20, backup_count=1) as log:
        log.append("measurement", {"bad": object()})
        log.append("measurement", {"seq": 1})
    assert [r["seq"] for r in read_records(tmp_path)] == [1]
    assert log.stats().dropped == 1


def test_unwritable_directory_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    log = JsonlLog(blocker / "log", max_bytes=4096, backup_count=1)
    with pytest.raises(JsonlLogError, match=r"set log\.dir to a writable directory"):
        log.start()


async def test_aclose_from_event_loop(tmp_path: Path) -> None:
    log = JsonlLog(tmp_path, max_bytes=1 << 20, backup_count=1)
    log.start()
    log.append("estimate", _estimate(1))
    assert await log.aclose()
    assert [r["seq"] for r in read_records(tmp_path)] == [1]
