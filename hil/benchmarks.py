"""``python -m hil bench``: every performance figure of issue 15, each against its baseline.

Each figure in ``bench.json`` has a value, the baseline it is compared against **measured in the
same run**, its goal and whether it holds. The component benchmarks run in their own processes
(timings do not interfere):

* ``hil.bench_core`` — core CPU per frame for every role (track, burst, transit, acquire), mean
  and p99, against the tuned OpenCV full-frame baseline on the same frames (ratio ≥ 10×);
* ``hil.bench_publish`` — core output → MQTT subscriber at 30 messages/s through the daemon's
  hand-off, payload conversion and publisher, against a bare MQTT client's floor;
* ``hil soak`` (the live daemon on the simulator) — frame delivered → subscriber latency (the
  service's own share, matched per frame through ``…/sim/truth``) at the daemon's estimate
  rate, service CPU without the simulator's render thread, start → first estimate with the
  kernels compiled ahead; a second, short start with an empty kernel cache;
* the RSS slope is the goal's own measurement, a 30-minute soak: the bench quotes the latest
  one committed (:data:`LONG_SOAK_FILE`, with its date, commit, length and estimate rate in the
  figure's name) and reports its own 2-minute run's slope beside it, without a verdict (RSS
  settles over the first minutes: bounded histories and caches filling);
* ``hil.bench_cli`` — every ``dffd … --help`` against a bare interpreter start;
* ``hil.bench_start`` — start → first depth of ``dffd run`` on its embedded default (the broker
  and dashboard ports moved), against start → first estimate of the same starts;
* ``hil.bench_visca`` and ``hil.bench_render`` — serial round trip, simulator render time;

and in this process: depth measurements per second against the limit the configuration allows
(with the limit's parts: motor travel, link, frames) on every scenario (:mod:`hil.bench_depth`),
and ``dffd replay``'s frames/s on a recording made here, against PNG decoding alone
(:mod:`hil.bench_replay`). The figures are built in :mod:`hil.bench_figures`.

``python -m hil bench --readme [README.md]`` rewrites the README's performance table from
``OUT/bench.json`` (:mod:`hil.bench_table`).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hil.bench_depth import depth_rates
from hil.bench_figures import PARTS, figures_from
from hil.bench_replay import replay_speed
from hil.bench_table import write_readme
from hil.soak import git_commit

__all__ = ["BENCH_SCHEMA", "run_bench", "write_readme"]


REPO_ROOT = Path(__file__).resolve().parent.parent
BENCH_SCHEMA = 2
# One component may take this long (the fresh-cache start compiles ~25 s of kernels on a loaded
# 2-core machine; the soak runs SOAK_S plus start-up); a hung one is killed and reported.
COMPONENT_TIMEOUT_S = 600.0
# The live daemon's measured run: long enough for a few thousand estimates.
SOAK_S = 120.0
# The latest long soak (`python -m hil soak --minutes 30 --out DIR`, DIR/soak.json copied here):
# the RSS slope the goal means, measured over 30 minutes (a shorter soak is not quoted:
# hil.bench_figures.LONG_SOAK_MIN_S).
LONG_SOAK_FILE = REPO_ROOT / "docs" / "soak-30min.json"
QUICK_SOAK_S = 12.0
# The part of :data:`hil.bench_figures.PARTS` each component process is in.
_COMPONENT_PART = {
    "bench_core": "core",
    "bench_publish": "publish",
    "bench_cli": "cli",
    "bench_visca": "visca",
    "bench_render": "render",
    "bench_start": "start",
}


def run_bench(out_dir: Path, *, quick: bool = False, only: Sequence[str] | None = None) -> int:
    """Run every benchmark (or the ``only`` parts of :data:`PARTS`), print the figures and
    write ``out_dir/bench.json`` (a partial run says which parts it holds under ``only``)."""
    unknown = sorted(set(only or ()) - set(PARTS))
    if unknown:
        raise ValueError(f"unknown bench part(s) {unknown}: choose from {', '.join(PARTS)}")
    parts = set(only) if only else set(PARTS)
    out_dir.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    soak_s = QUICK_SOAK_S if quick else SOAK_S
    components: dict[str, list[str]] = {
        "bench_core": ["--frames", "150" if quick else "900"],
        "bench_publish": ["--messages", "90" if quick else "900"],
        "bench_cli": ["--repeat", "2" if quick else "5"],
        "bench_visca": ["--n", "20" if quick else "200"],
        "bench_render": ["--frames", "30" if quick else "300"],
        "bench_start": ["--repeat", "1" if quick else "3"],
    }
    raw: dict[str, Any] = {}
    skipped = {"skipped": "not in --only"}
    for name, args in components.items():
        if _COMPONENT_PART[name] not in parts:
            raw[name] = skipped
            continue
        raw[name] = _component(f"hil.{name}", [*args, "--out", str(out_dir / f"{name}.json")])
    raw["soak"] = _soak(out_dir / "soak", soak_s, fresh=False) if "soak" in parts else skipped
    # The empty-cache start compiles every kernel (~15-25 s): the full run only.
    if "soak" not in parts:
        raw["soak_fresh"] = skipped
    else:
        raw["soak_fresh"] = (
            {"skipped": "--quick"} if quick else _soak(out_dir / "soak-fresh", 1.0, fresh=True)
        )
    raw["soak_long"] = _long_soak(LONG_SOAK_FILE) if "soak" in parts else skipped
    raw["depth_rate"] = depth_rates(quick) if "depth" in parts else skipped
    raw["replay"] = replay_speed(quick) if "replay" in parts else skipped
    figures = figures_from(raw, parts)
    doc = {
        "schema": BENCH_SCHEMA,
        "quick": quick,
        "only": sorted(parts) if only else None,
        "t": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "commit": git_commit(),
        # Other work on the machine slows every figure; the 1/5/15-minute load averages say how
        # much there was (2 cores: above 2 the bench shared them).
        "load_average": {"before": list(load_before), "after": list(os.getloadavg())},
        "figures": figures,
        "raw": raw,
    }
    path = out_dir / "bench.json"
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n", encoding="utf-8")
    for f in figures:
        verdict = {True: "PASS", False: "FAIL", None: "  - "}[f["ok"]]
        base = (
            "" if f["baseline_value"] is None else f" vs {f['baseline']} {f['baseline_value']:.4g}"
        )
        shown = "–" if f["value"] is None else f"{f['value']:.4g}"
        print(f"[{verdict}] {f['name']}: {shown} {f['unit']}{base}  (goal {f['goal']})")
    print(f"bench: {path}")
    return 0


# -- components (subprocesses) ---------------------------------------------------------------


def _component(module: str, args: list[str], *, out: Path | None = None) -> dict[str, Any]:
    """Run ``python -m module args``; its JSON result (``--out`` in ``args`` or ``out``)."""
    if importlib.util.find_spec(module) is None:
        return {"missing": f"{module} is not in this tree"}
    result = out if out is not None else Path(args[args.index("--out") + 1])
    cmd = [sys.executable, "-m", module, *args]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(  # noqa: S603 - this repository's own module
            cmd,
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=COMPONENT_TIMEOUT_S,
            check=False,
        )
    except subprocess.TimeoutExpired:
        return {"error": f"{module} did not finish within {COMPONENT_TIMEOUT_S:.0f} s"}
    if not result.exists():
        tail = (proc.stderr or proc.stdout)[-2000:]
        return {"error": f"{module} exited {proc.returncode} without results: {tail}"}
    data: dict[str, Any] = json.loads(result.read_text(encoding="utf-8"))
    data["_wall_s"] = time.perf_counter() - t0
    data["_exit"] = proc.returncode
    return data


def _long_soak(path: Path) -> dict[str, Any]:
    """The summary of the committed long soak (its series left out), or why there is none."""
    try:
        doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return {"missing": f"{path}: {exc}"}
    return {k: v for k, v in doc.items() if k not in ("rss_series", "windows")} | {
        "file": str(path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path)
    }


def _soak(out: Path, seconds: float, *, fresh: bool) -> dict[str, Any]:
    args = ["soak", "--seconds", f"{seconds:g}", "--out", str(out)]
    if fresh:
        args.append("--fresh-kernel-cache")
    return _component("hil", args, out=out / "soak.json")
