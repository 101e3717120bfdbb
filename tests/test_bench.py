"""The performance bench: its figures, the README table made from them, its quick components."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.bench_cli import measure as measure_help
from hil.bench_figures import figures_from
from hil.bench_table import END, SNAPSHOT, START, readme_table, replace_block, write_readme
from hil.soak import thread_shares

REPO = Path(__file__).resolve().parent.parent

# What issue 15 asks bench.json to hold (the depth figures come one per scenario).
ISSUE_15_KEYS = {
    "latency_p50", "latency_p99", "core_vs_tuned", "service_cpu", "replay_fps",
    "first_estimate_warm", "first_estimate_fresh", "rss_slope", "help_dffd", "help_run",
    "help_replay", "help_sim-camera", "first_depth_warm",
    *(f"core_{r}_{s}" for r in ("track", "burst", "transit", "acquire") for s in ("mean", "p99")),
}  # fmt: skip


def _raw() -> dict:
    """Component results in the shapes the components write them (values made up)."""
    role = {"n": 10, "mean_ms": 0.4, "p99_ms": 1.2}
    limit = {
        "depth_hz": 2.5, "cycle_frames": 12, "move_s": [0.12, 0.12],
        "motor_travel_s": [0.09, 0.09], "link_s_per_move": 0.029,
    }  # fmt: skip
    return {
        "soak": {
            "estimate_hz": 30.0,
            "latency_ms": {"delivered_to_subscriber": {"p50": 2.5, "p99": 9.0}},
            "service_cpu_pct_one_core": 8.0,
            "cpu_pct_one_core": 20.0,
            "start_to_first_estimate_s": 3.0,
            "rss_mib": {"slope_mib_per_hour": 0.2, "min": 200.0},
            "run_s": 120.0,
        },
        "soak_fresh": {"start_to_first_estimate_s": 20.0},
        "bench_publish": {
            "rate_hz": 30.0,
            "floor": {"p50_ms": 0.8, "p99_ms": 3.0},
            "path": {"p50_ms": 1.0, "p99_ms": 4.0},
        },
        "bench_core": {
            "core_by_role": dict.fromkeys(("track", "burst", "transit", "acquire"), role),
            "baseline_tuned_full_frame": {"mean_ms": 4.4},
            "baseline_naive_full_frame": {"mean_ms": 9.0},
        },
        "replay": {"frames": 900, "replay_fps": 1100.0, "decode_one_thread_fps": 500.0},
        "bench_cli": {
            "baseline_s": 0.05,
            "help_s": {"dffd --help": 0.1}
            | {f"dffd {c} --help": 0.1 for c in ("run", "replay", "sim-camera")},
        },
        "depth_rate": {"static": {"steady_depth_hz": 2.4, "limit": limit}},
        "bench_start": {
            "median_first_estimate_s": 2.1,
            "median_first_depth_s": 4.6,
            "runs": [{"first_depth_m": 9.9, "first_depth_truth_m": 10.0}],
        },
    }


def test_every_issue_15_figure_has_value_baseline_goal_and_verdict() -> None:
    figures = figures_from(_raw())
    keys = {f["key"] for f in figures}
    assert keys >= ISSUE_15_KEYS
    assert "depth_ratio_static" in keys
    for f in figures:
        assert f["goal"], f
        if f["key"] in ISSUE_15_KEYS:
            assert f["value"] is not None, f
            assert f["baseline_value"] is not None, f
            assert f["ok"] in (True, False), f
    by_key = {f["key"]: f for f in figures}
    assert by_key["core_vs_tuned"]["value"] == pytest.approx(11.0)
    assert by_key["core_vs_tuned"]["ok"] is True
    assert by_key["latency_p99"]["ok"] is False  # 9 ms against 8 ms
    assert by_key["depth_ratio_static"]["value"] == pytest.approx(0.96)
    assert "motor 90/90 + link 29 ms" in by_key["depth_ratio_static"]["name"]
    assert by_key["first_depth_warm"]["ok"] is True  # 4.6 s against 5 s
    assert "off by ≤ 0.10 m" in by_key["first_depth_warm"]["name"]


def test_rss_slope_quotes_the_long_soak_and_reports_the_short_run() -> None:
    long = {
        "run_s": 1800.0, "estimate_hz": 30.0, "commit": "abc1234", "t": "2026-11-24T01:14:00Z",
        "file": "docs/soak-30min.json",
        "rss_mib": {"slope_mib_per_hour": -0.4, "min": 250.0, "slope_from_s": 900.0},
    }  # fmt: skip
    by_key = {f["key"]: f for f in figures_from(_raw() | {"soak_long": long})}
    rss = by_key["rss_slope"]
    assert rss["value"] == pytest.approx(-0.4)
    assert rss["ok"] is True
    assert "30-minute soak" in rss["name"]
    assert "abc1234" in rss["name"]
    assert "2026-11-24T01:14:00Z" in rss["name"]
    short = by_key["rss_slope_bench_run"]
    assert short["value"] == pytest.approx(0.2)
    assert short["ok"] is None
    # A soak shorter than the goal's 30 minutes is not quoted: the bench's own run decides.
    brief = long | {"run_s": 600.0}
    by_key = {f["key"]: f for f in figures_from(_raw() | {"soak_long": brief})}
    assert by_key["rss_slope"]["value"] == pytest.approx(0.2)
    assert "rss_slope_bench_run" not in by_key


def test_missing_components_give_figures_without_values() -> None:
    figures = figures_from({})
    assert figures, "the core figures are listed even when nothing was measured"
    assert all(f["value"] is None and f["ok"] is None for f in figures)


def test_readme_performance_table_is_what_the_generator_makes_of_the_snapshot() -> None:
    doc = json.loads(SNAPSHOT.read_text(encoding="utf-8"))
    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = text.split(START, 1)[1].split(END, 1)[0].strip("\n")
    assert block == readme_table(doc), "regenerate: python -m hil bench --out DIR --readme"


def test_write_readme_replaces_only_the_block(tmp_path: Path) -> None:
    bench = tmp_path / "bench.json"
    bench.write_text(json.dumps({"commit": "abc", "t": "T", "figures": figures_from(_raw())}))
    readme = tmp_path / "README.md"
    readme.write_text(f"# Title\n\nbefore\n{START}\nold table\n{END}\nafter\n")
    snapshot = tmp_path / "figures.json"
    assert write_readme(bench, readme, snapshot) == 0
    text = readme.read_text()
    assert text.startswith("# Title\n\nbefore\n")
    assert text.endswith(f"{END}\nafter\n")
    assert "old table" not in text
    assert "| frame delivered → MQTT subscriber p50" in text
    assert json.loads(snapshot.read_text())["figures"][0]["key"] == "latency_p50"
    with pytest.raises(ValueError, match="bench:start"):
        replace_block("no markers here", "table")


def test_thread_shares_are_percent_of_a_core() -> None:
    first = {"dffd-loop": 1.0, "asyncio_0": 2.0}
    last = {"dffd-loop": 1.5, "asyncio_0": 3.0, "dffd-estimator": 0.25}
    shares = thread_shares(first, last, 10.0)
    assert shares == pytest.approx({"dffd-loop": 5.0, "asyncio_0": 10.0, "dffd-estimator": 2.5})


@pytest.mark.timeout(60)
def test_help_timings_cover_every_subcommand() -> None:
    from dffd.cli import SUBCOMMANDS

    result = measure_help(1)
    assert set(result["help_s"]) == {"dffd --help"} | {f"dffd {c} --help" for c in SUBCOMMANDS}
    assert all(s > 0 for s in result["help_s"].values())
    assert result["baseline_s"] > 0


@pytest.mark.timeout(60)
async def test_publish_path_bench_measures_both_modes() -> None:
    from hil.bench_publish import measure

    result = await measure(20, 50.0)
    for mode in ("floor", "path"):
        assert result[mode]["n"] == 20
        assert 0 < result[mode]["p50_ms"] <= result[mode]["p99_ms"]


def test_only_core_keeps_the_core_figures_named_for_the_service_trackers() -> None:
    from hil.benchmarks import run_bench

    raw = _raw()
    raw["bench_core"]["trackers"] = ["mmae"]
    for name in ("soak", "soak_fresh", "bench_publish", "replay", "bench_cli", "depth_rate"):
        raw[name] = {"skipped": "not in --only"}  # as run_bench records a part not run
    figures = figures_from(raw, {"core"})
    keys = {f["key"] for f in figures}
    roles = ("track", "burst", "transit", "acquire")
    per_role = {f"core_{r}_{s}" for r in roles for s in ("mean", "p99")}
    assert keys == {*per_role, "core_vs_tuned", "core_vs_naive"}
    # The figure certifies what users run: the pipeline and the service's tracker, by name.
    assert all("mmae" in f["name"] for f in figures if f["key"] != "core_vs_naive")
    with pytest.raises(ValueError, match="unknown bench part"):
        run_bench(Path("unused"), only=["cores"])


def test_a_timed_start_reaches_a_first_depth_and_leaves_nothing_in_tmp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import tempfile

    from hil.bench_start import measure_start

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    run = measure_start()
    assert run["error"] is None
    assert run["first_estimate_s"] is not None
    assert run["first_depth_s"] is not None
    assert run["first_depth_s"] >= run["first_estimate_s"]
    # a good start's daemon log and work directory are removed; a failed one's are kept
    assert list(tmp_path.glob("hil-start-*")) == []
