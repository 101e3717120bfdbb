"""The bench's replay part: ``dffd replay``'s frames/s on a lock-step recording made here,
against PNG decoding alone, and each PNG encoding's decoding and encoding cost.

Run in ``python -m hil bench``'s own process (:mod:`hil.benchmarks`); its figures are built in
:mod:`hil.bench_figures`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

# The replay recording: a static target at 4 m.
REPLAY_SCENARIO = "static"
REPLAY_CASE = "z4m"
REPLAY_DURATION_S = 30.0
QUICK_REPLAY_DURATION_S = 6.0
# Frames re-encoded in each PNG encoding to compare their decoding cost.
DECODE_SAMPLE_FRAMES = 200


def replay_speed(quick: bool) -> dict[str, Any]:
    """Record a lock-step session, then time ``dffd replay`` on it and PNG decoding alone."""
    import cv2

    from dffd.core.lens import Lens
    from dffd.recording import RecordingReader, RecordingWriter
    from dffd.replay import run as replay_cli
    from hil.lockstep import run_session
    from hil.runner import RecordingSink
    from hil.scenario import load_scenario
    from hil.simbuild import build_session

    duration = QUICK_REPLAY_DURATION_S if quick else REPLAY_DURATION_S
    scenario = load_scenario(REPLAY_SCENARIO)
    traj = dict(scenario.expand())[REPLAY_CASE]
    seed = scenario.seeds[0]
    session = build_session(scenario, traj, seed)
    lens = Lens.from_toml(session.lens_path)
    with tempfile.TemporaryDirectory(prefix="hil-bench-replay-") as tmp:
        rec = Path(tmp) / "rec"
        t0 = time.perf_counter()
        with RecordingWriter(rec, session.fps, session.frame_size, lens.to_meta()) as writer:
            run_session(
                scenario,
                REPLAY_CASE,
                traj,
                seed,
                duration_s=duration,
                recorder=RecordingSink(writer),
            )
        record_s = time.perf_counter() - t0
        reader = RecordingReader(rec)
        n = len(reader)
        png_bytes = sum((rec / r.file).stat().st_size for r in reader.records)
        t0 = time.perf_counter()
        for r in reader.records:
            cv2.imread(str(rec / r.file), cv2.IMREAD_UNCHANGED)
        decode_s = time.perf_counter() - t0
        encodings = _decode_cost(rec, reader.records[:DECODE_SAMPLE_FRAMES])
        args = argparse.Namespace(
            run=rec, out=Path(tmp) / "est.jsonl", config=None, summary=None, plot=None,
            roi=None, settle=None, known_size=None, best=None,
        )  # fmt: skip
        t0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
        code = replay_cli(args)
        replay_s = time.perf_counter() - t0
        main_cpu, all_cpu = time.thread_time() - c0, time.process_time() - p0
    return {
        "what": f"{REPLAY_SCENARIO}/{REPLAY_CASE}, {duration:g} s lock-step recording",
        "frames": n,
        "png_mib": png_bytes / 2**20,
        "record_s": record_s,
        "decode_one_thread_s": decode_s,
        "decode_one_thread_fps": n / decode_s if decode_s > 0 else None,
        "replay_s": replay_s,
        "replay_fps": n / replay_s if replay_s > 0 else None,
        # The core runs in the calling thread, decoding in a pool beside it: on 2 idle cores the
        # rate is bound by the calling thread's CPU per frame or by half the process's.
        "main_thread_cpu_ms_per_frame": 1e3 * main_cpu / n if n else None,
        "process_cpu_ms_per_frame": 1e3 * all_cpu / n if n else None,
        "cpu_bound_fps_2_cores": n / max(main_cpu, all_cpu / 2.0) if n and all_cpu > 0 else None,
        "replay_exit": code,
        "png_encodings": encodings,
    }


def _decode_cost(rec: Path, records: list[Any]) -> dict[str, Any]:
    """CPU per frame to decode and encode the same frames in each PNG encoding (from memory)."""
    import cv2
    import numpy as np

    from dffd.recording import PNG_PARAMS

    read = (cv2.imread(str(rec / r.file), cv2.IMREAD_UNCHANGED) for r in records)
    images = [im for im in read if im is not None]
    out: dict[str, Any] = {}
    for name, params in PNG_PARAMS.items():
        c0 = time.thread_time()
        blobs = [cv2.imencode(".png", im, list(params))[1] for im in images]
        encode = time.thread_time() - c0
        c0 = time.thread_time()
        for blob in blobs:
            cv2.imdecode(np.asarray(blob), cv2.IMREAD_UNCHANGED)
        decode = time.thread_time() - c0
        n = max(1, len(images))
        out[name] = {
            "frames": len(images),
            "kib_per_frame": sum(b.nbytes for b in blobs) / n / 1024,
            "decode_cpu_ms": 1e3 * decode / n,
            "encode_cpu_ms": 1e3 * encode / n,
        }
    return out
