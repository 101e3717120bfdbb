"""Per-frame CPU of the estimation core vs a naive full-frame baseline (DESIGN §8, issue 4).

Both run in the same process on the same pre-rendered 640×480 frames (a disc about 100 px
across, moving and growing, 64 normals), single-threaded OpenCV, CPU time of the calling thread.

    python -m hil.bench_core [--frames 300] [--out bench_core.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from dffd.core.contour import outward_normals, resample_closed
from dffd.core.focus import focus_cost
from dffd.core.pipeline import Pipeline, PipelineConfig
from dffd.core.synthetic import render_disc, synthetic_lens
from dffd.core.types import FrameTag
from drivers.frames import Frame

TARGET_MS = 2.0
TARGET_RATIO = 10.0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark, print the figures and the ratio, write JSON to ``--out``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--out", type=Path, default=None, help="JSON result file")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    lens = synthetic_lens()
    counts = lens.counts_for_depth(2.0)
    frames = _frames(args.frames)

    pipe = Pipeline(PipelineConfig(), lens)
    _warm_up(pipe, counts)
    tag = FrameTag("track", counts, 0.0, 0.0)
    core = _measure(lambda f: pipe.process(f, tag), frames)
    assert pipe.state == "tracking", "the benchmark target was lost"
    naive = _measure(_naive_frame, frames)
    ratio = naive["mean_ms"] / core["mean_ms"]
    result: dict[str, Any] = {
        "schema": 1,
        "what": "estimator CPU per tracking frame, 640x480, 64 normals, target ~100 px across",
        "frames": len(frames),
        "core": core,
        "baseline_naive_full_frame": naive,
        "speedup": ratio,
        "targets": {"core_mean_ms_max": TARGET_MS, "speedup_min": TARGET_RATIO},
        "pass": core["mean_ms"] <= TARGET_MS and ratio >= TARGET_RATIO,
        "machine": {
            "python": sys.version.split()[0],
            "platform": platform.platform(),
            "opencv_threads": cv2.getNumThreads(),
        },
    }
    print(
        f"core : mean {core['mean_ms']:.3f} ms  p50 {core['p50_ms']:.3f}  "
        f"p95 {core['p95_ms']:.3f}  (target <= {TARGET_MS} ms)"
    )
    print(
        f"naive: mean {naive['mean_ms']:.3f} ms  p50 {naive['p50_ms']:.3f}  "
        f"p95 {naive['p95_ms']:.3f}"
    )
    verdict = "PASS" if result["pass"] else "FAIL"
    print(f"speedup {ratio:.1f}x (target >= {TARGET_RATIO}x) -> {verdict}")
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")
    return 0


def _frames(n: int) -> list[Frame]:
    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        c = (320 + 40 * math.sin(k / 25), 240 + 20 * math.cos(k / 31))
        r = 50.0 * (1 + 0.05 * math.sin(k / 40))
        out.append(Frame(k + 1000, (k + 1000) / 30, render_disc(640, 480, c, r, 0.0, rng=rng)))
    return out


def _warm_up(pipe: Pipeline, counts: int) -> None:
    """Acquire and complete bursts so that every filter runs in the measured frames."""
    rng = np.random.default_rng(1)
    lens = pipe.lens
    k = 0
    for burst in range(4):
        for _ in range(3):
            img = render_disc(640, 480, (320, 240), 50.0, 0.0, rng=rng)
            pipe.process(Frame(k, k / 30, img), FrameTag("track", counts, 0.0, 0.0))
            k += 1
        for slot, c in enumerate(pipe.plan_burst(counts)):
            blur = lens.blur_radius_px(lens.v_from_counts(c), lens.v_from_counts(counts), 2.9)
            img = render_disc(640, 480, (320, 240), 50.0, blur, rng=rng)
            pipe.process(Frame(k, k / 30, img), FrameTag("burst", c, 0.0, 0.0, (burst, slot)))
            k += 1


def _measure(fn: Callable[[Frame], object], frames: Sequence[Frame]) -> dict[str, float]:
    times = []
    for f in frames:
        t0 = time.thread_time_ns()
        fn(f)
        times.append((time.thread_time_ns() - t0) / 1e6)
    a = np.asarray(times)
    return {
        "mean_ms": float(a.mean()),
        "p50_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(a.max()),
    }


def _naive_frame(frame: Frame) -> float | None:
    """Full-frame gradient + full-frame contour search + cost from the full-frame gradient."""
    gray = frame.image.astype(np.float32)
    smooth = cv2.GaussianBlur(gray, (0, 0), 1.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    mag = gx * gx + gy * gy
    u8 = cv2.GaussianBlur(frame.image, (5, 5), 1.0)
    _, binary = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(binary, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    best = max(contours, key=cv2.contourArea)
    pts = resample_closed(best.reshape(-1, 2).astype(np.float64), 64)
    normals = outward_normals(pts)
    return _cost_along_normals(mag, pts, normals)


def _cost_along_normals(
    mag: npt.NDArray[np.float32], pts: npt.NDArray[np.float64], normals: npt.NDArray[np.float64]
) -> float | None:
    steps = np.arange(-12, 13)
    xs = np.clip(np.rint(pts[:, 0:1] + steps * normals[:, 0:1]), 0, mag.shape[1] - 1).astype(int)
    ys = np.clip(np.rint(pts[:, 1:2] + steps * normals[:, 1:2]), 0, mag.shape[0] - 1).astype(int)
    peaks = mag[ys, xs].max(axis=1).astype(np.float64)
    cost = focus_cost(peaks)
    return None if cost is None else cost[0]


if __name__ == "__main__":
    sys.exit(main())
