"""The HIL bench: scenarios, a short lock-step run end to end, report fields, baselines, compare."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.baselines import known_size_depth, square_side_for_size, sweep_depth
from hil.cli import main as hil_main
from hil.compare import compare_reports
from hil.compare import main as compare_main
from hil.scenario import SCENARIO_NAMES, ScenarioError, available_scenarios, load_scenario

# A few seconds of a static target at 2 m, where acquisition and the first wide burst work: the
# whole chain (sim + VISCA device + scheduler + core + every baseline pass) runs in lock-step.
SHORT_SCENARIO = """
name = "short-static"
description = "test: disc at 2 m, a few seconds"
duration_s = 6.0
settle_s = 3.0
seeds = [5]

[target]
shape = "disc"
size_m = 0.03576
known_size_m = 0.03576

[trajectory]
kind = "static"
position_m = [0.0, 0.0, 2.0]

[baselines]
full_sweep_settings = 8
max_pass_s = 6.0

[thresholds]
ss_std_max_m = 0.0377
ss_std_vs_measured_max = 0.5
sweep_rate_ratio_min = 5.0
"""


# A calibration on five depths over the working range (15 by default: ~45 s).
QUICK_CALIBRATION = ["--calibration-depths", "1.5,2.5,4,7,13"]


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    base = tmp_path_factory.mktemp("hil")
    scenario = base / "short-static.toml"
    scenario.write_text(SHORT_SCENARIO, encoding="utf-8")
    out = base / "out"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        # the simulator's own lens table: the calibration (the default, ~8 s more) has its
        # own test below
        argv = ["run", str(scenario), "--fast", "--out", str(out), "--no-progress"]
        code = hil_main([*argv, "--record", "--simulator-table"])
    (base / "stdout.txt").write_text(printed.getvalue(), encoding="utf-8")
    assert code == 0
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    return out, report


def test_every_named_scenario_loads() -> None:
    assert set(SCENARIO_NAMES) <= set(available_scenarios())
    for name in SCENARIO_NAMES:
        scenario = load_scenario(name)
        sessions = scenario.expand()
        assert sessions
        assert scenario.settle_s < scenario.duration_s
        assert scenario.target.size_m == pytest.approx(0.03576)
    static = load_scenario("static")
    depths = [traj.position_m[2] for _, traj in static.expand()]
    assert min(depths) <= 2.0
    assert max(depths) == 10.0
    circle = load_scenario("paper-circle")
    c, r = circle.trajectory.center_m[2], circle.trajectory.radius_m
    assert (c - r, c + r) == (pytest.approx(2.0), pytest.approx(10.0))


def test_unknown_scenario_and_bad_settings_are_explained() -> None:
    with pytest.raises(ScenarioError, match="known scenarios"):
        load_scenario("no-such-scenario")
    scenario = load_scenario("approach")
    changed = scenario.with_settings(["scheduler.snap_counts=400", "camera.lens.psf=gaussian"])
    assert changed.scheduler == {"snap_counts": 400}
    assert changed.camera.overrides == {"lens.psf": "gaussian"}
    with pytest.raises(ScenarioError, match="expected scheduler"):
        scenario.with_settings(["snap_counts=400"])


def test_short_fast_run_reports_sane_accuracy(short_run: tuple[Path, dict]) -> None:
    _, report = short_run
    assert report["scenario"] == "short-static"
    assert report["mode"] == "fast"
    assert "calibration" not in report  # --simulator-table: no calibrated table, no block
    est = report["estimators"]
    for name in ("measured", "cf1", "cf2", "lpv", "kf"):
        block = est[name]
        assert set(block) >= {"n", "bias_m", "std_m", "rms_m", "ss_std_m", "p95_abs_m"}
        assert block["n"] >= 1
        # A static disc at 2 m: every estimator within a few centimetres.
        assert abs(block["bias_m"]) < 0.05, name
        assert block["rms_m"] < 0.05, name
    assert est["lpv"]["n"] > est["measured"]["n"]  # estimates per frame, measurements per burst
    assert report["best"] == "lpv"
    bursts = report["bursts"]
    assert bursts["accepted"] >= 2
    # every burst without a depth is counted with its reason (fits rejected, bursts dropped)
    reasons = bursts["reasons"]
    assert bursts["rejected"] + bursts["dropped"] == sum(reasons.values())
    assert bursts["dropped"] == sum(n for r, n in reasons.items() if r.startswith("dropped: "))
    assert bursts["measure_fallbacks"] == 0  # the default measure is the paper's cost (2)


def test_each_baseline_yields_numbers(short_run: tuple[Path, dict]) -> None:
    _, report = short_run
    for key in ("known_size", "aruco", "full_sweep", "coarse_fine"):
        block = report["baselines"][key]
        assert block is not None, key
        assert block["n"] >= 1, key
        assert math.isfinite(block["rms_m"]), key
        assert block["rms_m"] < 0.5, key  # each is a working depth estimate at 2 m
    # Krotkov's coarse-to-fine search: finer than the full sweep at a comparable frame cost
    assert report["rates"]["coarse_fine_depth_hz"] > 0
    fine, full = report["baselines"]["coarse_fine"], report["baselines"]["full_sweep"]
    assert fine["rms_m"] < full["rms_m"]


def test_rates_latency_cpu_and_goals_present(short_run: tuple[Path, dict]) -> None:
    out, report = short_run
    rates = report["rates"]
    assert rates["depth_hz"] > 0
    assert rates["depth_limit_hz"] > 0
    assert rates["full_sweep_depth_hz"] > 0
    assert rates["depth_rate_ratio"] == pytest.approx(rates["depth_hz"] / rates["depth_limit_hz"])
    assert report["latency"] is None  # virtual time: no exposure → MQTT latency
    cpu = report["cpu"]
    assert 0 < cpu["core_ms_per_frame_mean"] < 100
    assert cpu["speedup_vs_real_time"] > 0  # a figure for the bench, not a timed assertion
    goals = {g["goal"] for g in report["goals"]}
    assert any("full_sweep" in g for g in goals)
    assert any("ss_std" in g for g in goals)
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert any(p.endswith("-depth.png") for p in pngs)
    assert any(p.endswith("-parabolas.png") for p in pngs)


def test_report_scores_every_3d_tracker_against_the_3d_truth(
    short_run: tuple[Path, dict],
) -> None:
    out, report = short_run
    block = report["tracking_3d"]
    assert set(block) == {"mmae", "imm", "cv"}
    for name, b in block.items():
        assert b["n"] > 10, name
        # A disc at rest 2 m away: the 3D position is as good as the fused depth (cm).
        assert 0 < b["position_rms_m"] < 0.1, name
        assert math.isfinite(b["velocity_rms_m_s"]), name
        assert math.isfinite(b["acceleration_rms_m_s2"]), name
        w = b["angular_speed"]
        assert w["truth_mean_rad_s"] == 0.0
        assert abs(w["bias_rad_s"]) <= w["rms_rad_s"] < 1.0, name
    assert block["cv"]["angular_speed"] == {
        "bias_rad_s": 0.0,
        "rms_rad_s": 0.0,
        "truth_mean_rad_s": 0.0,
    }
    assert (out / "short-static-model-probabilities.png").stat().st_size > 1000


def test_record_writes_a_replayable_recording(short_run: tuple[Path, dict]) -> None:
    from dffd.recording import RecordingReader

    out, report = short_run
    rec = out / "recording" / "short-static"
    assert (rec / "meta.json").exists()
    reader = RecordingReader(rec)
    assert len(reader) == round(6.0 * reader.fps)
    roles = {tag.role for _, tag in reader}
    assert {"track", "burst"} <= roles
    truth = reader.truth
    assert truth is not None
    # The 3D truth in the world frame beside the camera-frame depth: the disc rests at (0, 0, 2).
    # The camera-frame depth moves with the head: a centring move of a few tenths of a degree
    # (the first, blurred frames' centroids scatter by ~1 px) changes it by ~10 µm.
    np.testing.assert_allclose(truth.z_m, 2.0, atol=1e-4)
    np.testing.assert_allclose(truth.extra["z_world_m"], 2.0, atol=1e-6)
    np.testing.assert_allclose(truth.extra["x_world_m"], 0.0, atol=1e-6)
    for name in ("vx_world_m_s", "az_world_m_s2", "angular_speed_rad_s"):
        np.testing.assert_allclose(truth.extra[name], 0.0, atol=1e-9)
    assert report["duration_s"] == pytest.approx(6.0)


def test_compare_flags_a_regression(short_run: tuple[Path, dict], tmp_path: Path) -> None:
    out, report = short_run
    same = compare_reports(report, report)
    assert same
    assert not any(f.regressed for f in same)
    worse = copy.deepcopy(report)
    worse["estimators"]["lpv"]["ss_std_m"] = report["estimators"]["lpv"]["ss_std_m"] * 3 + 0.01
    worse["rates"]["depth_hz"] = report["rates"]["depth_hz"] * 0.5
    findings = {f.metric: f for f in compare_reports(report, worse)}
    assert findings["estimators.lpv.ss_std_m"].regressed
    assert findings["rates.depth_hz"].regressed
    assert not findings["estimators.cf2.ss_std_m"].regressed
    worse_path = tmp_path / "worse.json"
    worse_path.write_text(json.dumps(worse), encoding="utf-8")
    assert compare_main(out / "report.json", worse_path) == 1
    assert compare_main(out / "report.json", out / "report.json") == 0


def test_known_size_and_sweep_baselines_on_exact_inputs() -> None:
    from dffd.core.synthetic import synthetic_lens

    # z = f R / r: 31 mm, 5 µm pixels, R = 35.76 mm, r = 110.856 px → 2 m
    assert known_size_depth(110.856, 0.03576, 31.0, 0.005) == pytest.approx(2.0, rel=1e-4)
    assert square_side_for_size(1.0) == pytest.approx(math.sqrt(3.0))
    lens = synthetic_lens()
    true_z = 3.0
    v_true = lens.v_from_depth(true_z)
    counts = np.linspace(lens.counts_range[0], lens.counts_range[1], 16).round().astype(int)
    v = lens.v_from_counts_array(counts)
    sharp = np.exp(-(((v - v_true) / 0.05) ** 2))  # Gaussian in v: the log-parabola is exact
    z = sweep_depth(counts.tolist(), sharp.tolist(), lens)
    assert z == pytest.approx(true_z, rel=0.02)


@pytest.mark.timeout(120)
def test_soak_writes_its_figures_and_plot(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    assert hil_main(["soak", "--seconds", "4", "--window", "1", "--out", str(out)]) == 0
    result = json.loads((out / "soak.json").read_text())
    assert result["estimates"] > 0
    assert result["start_to_first_estimate_s"] > 0
    assert result["cpu_pct_one_core"] > 0
    assert result["rss_mib"]["min"] > 0
    # which part of RSS grows: anonymous memory or mapped files (libraries' pages)
    assert result["rss_mib"]["anon_last_mib"] > 0
    assert result["rss_mib"]["file_last_mib"] > 0
    assert result["rss_mib"]["anon_last_mib"] + result["rss_mib"]["file_last_mib"] == (
        pytest.approx(result["rss_series"][-1][1], abs=1.0)
    )
    lat = result["latency_ms"]["exposure_to_subscriber"]
    assert 0 < lat["p50"] <= lat["p99"] <= lat["max"]
    assert len(result["windows"]) >= 3
    assert all(w["estimate_hz"] >= 0 for w in result["windows"])
    assert (out / "soak.png").stat().st_size > 0
    # the service's own share: estimates matched with their frame's delivery (…/sim/truth)
    own = result["latency_ms"]["delivered_to_subscriber"]
    assert result["latency_ms"]["delivered_matched"] > 0
    assert 0 < own["p50"] < lat["p50"]
    # per-thread CPU by kernel thread name: the estimator and the simulator's renderer apart
    assert "dffd-estimator" in result["thread_cpu_pct_one_core"]
    assert 0 <= result["service_cpu_pct_one_core"] <= result["cpu_pct_one_core"]


def test_optics_flag_and_seed_list_give_a_spread_over_seeds(tmp_path: Path) -> None:
    """--optics aberrated renders with the second optics model and tells the estimator that
    model's own lens table; --seeds runs each seed and the report gives mean and spread."""
    from hil.report import load_report
    from hil.report_tables import accuracy_table, markdown_table
    from hil.simbuild import build_session

    scenario = tmp_path / "short-static.toml"
    scenario.write_text(SHORT_SCENARIO, encoding="utf-8")
    aberrated = load_scenario(scenario).with_optics("aberrated")
    session = build_session(aberrated, aberrated.trajectory, 5)
    assert session.config.optics.model == "aberrated"
    assert 'name = "sim-aberrated"' in session.lens_path.read_text(encoding="utf-8")
    out = tmp_path / "out"
    argv = ["run", str(scenario), "--fast", "--out", str(out), "--no-progress", "--no-plots"]
    argv += ["--no-baselines", "--optics", "aberrated", "--seeds", "5,6", "--simulator-table"]
    assert hil_main(argv) == 0
    report = load_report(out)
    assert report["optics"] == "aberrated"
    spread = report["seeds"]
    assert [row["seed"] for row in spread["per_seed"]] == [5, 6]
    rms = [row["best_ss_rms_m"] for row in spread["per_seed"]]
    assert spread["mean"]["best_ss_rms_m"] == pytest.approx(np.mean(rms))
    assert spread["sd"]["best_ss_rms_m"] == pytest.approx(np.std(rms, ddof=1))
    assert all(r < 0.1 for r in rms)  # a static disc at 2 m, on a lens it was not tuned on
    row = markdown_table([report]).splitlines()[-1]
    assert "| aberrated | 2 |" in row
    # issue 11's table: ratio, coverage, estimate rate and the closed-loop focus slope
    slope = report["focus_slope"]
    assert slope["n"] > 10
    assert slope["slope"] == pytest.approx(1.0, abs=0.3)  # little spread of offsets at rest
    cells = accuracy_table([report]).splitlines()[-1].split(" | ")
    assert cells[1:3] == ["aberrated", "2"]
    ratio = spread["mean"]["best_ss_rms_m"] / spread["mean"]["measured_ss_std_m"]
    assert cells[5] == f"{ratio:.2f}"
    # the pooled coverage and each seed's own (lowest–highest) beside it
    own = [row["best_coverage_2sigma"] for row in spread["per_seed"]]
    pooled = report["estimators"][report["best"]]["coverage_2sigma"]
    assert min(own) <= pooled <= max(own)
    assert cells[6] == f"{pooled:.3f} ({min(own):.2f}–{max(own):.2f})"
    assert hil_main(["run", str(scenario), "--fast", "--seeds", "1,x"]) == 2


def test_recording_plan_says_the_size_and_warns_before_the_disk_fills() -> None:
    from hil.runner import recording_plan

    # 640x480 gray at 30 fps: 553 MB/min raw, and as much as stored PNG (measured 555 MB/min).
    plan, warning = recording_plan((640, 480), 30.0, 120.0, free_bytes=100 * 10**9)
    assert "~553 MB per minute of scenario (553 MB/min uncompressed)" in plan
    assert "this run ~1106 MB" in plan
    assert warning is None
    _, warning = recording_plan((640, 480), 30.0, 120.0, free_bytes=5 * 10**9)
    assert warning is not None
    assert "last only ~9 min" in warning
    _, warning = recording_plan((640, 480), 30.0, 120.0, free_bytes=300 * 10**6)
    assert warning is not None
    assert "does not fit" in warning


def test_a_recording_run_says_what_it_will_write_and_what_it_wrote(
    short_run: tuple[Path, dict],
) -> None:
    out, _ = short_run
    printed = (out.parent / "stdout.txt").read_text(encoding="utf-8")
    assert "MB per minute of scenario" in printed.splitlines()[0]  # up front
    (recording,) = (out / "recording").iterdir()
    frames = len(list(recording.glob("frames/*.png")))
    assert f"recording: {recording} ({frames} frames, " in printed  # and what it wrote


def test_bench_scores_on_a_table_dffd_calibrate_fitted(tmp_path: Path) -> None:
    """By default the lens table is fitted by dffd calibrate --sim on the session's camera
    (cached in the run directory) and its error against the simulator's true focus curve and
    the fit's residuals are reported; --simulator-table scores on the simulator's own."""
    from dffd.core.lens import Lens
    from hil.calibration import calibration_error

    scenario = tmp_path / "short-static.toml"
    scenario.write_text(SHORT_SCENARIO, encoding="utf-8")
    out = tmp_path / "out"
    argv = ["run", str(scenario), "--fast", "--out", str(out), "--no-progress", "--no-plots"]
    argv += ["--no-baselines", "--record", "--duration", "3", *QUICK_CALIBRATION]
    with contextlib.redirect_stdout(io.StringIO()):
        assert hil_main(argv) == 0
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    calib = report["calibration"]
    (table,) = calib["tables"]
    assert table["optics"] == "reference"
    assert table["seed"] == 5
    assert Path(table["table"]).parent == out / "calibration"
    # a fitted table over 1.5-12 m: not exact, within a few centimetres (measured 14 mm)
    assert 0 < table["depth_err_rms_m"] < 0.05
    assert table["depths_m"] == [1.5, 2.5, 4.0, 7.0, 13.0]
    assert table["fit"]["residual_v_rms_um"] < 2.0
    assert table["fit"]["rejected_depths_m"] == []
    assert table["fit"]["axis"] == "polynomial"  # the reference cam: no switch (§16)
    assert 0 <= table["fit"]["axis_misfit_sigma"] < 3.0
    assert calib["depth_err_rms_m_max"] == table["depth_err_rms_m"]
    lens = Lens.from_toml(Path(table["table"]))
    assert lens.name == "calibrated-reference-s5"
    # the recording carries the table the estimator was told
    meta = json.loads((out / "recording" / "short-static" / "meta.json").read_text("utf-8"))
    assert meta["lens"]["name"] == lens.name
    assert calibration_error(lens, lens)["depth_err_rms_m"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.timeout(120)
def test_soak_probe_samples_the_heap_inside_the_daemon(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    args = ["soak", "--seconds", "3", "--window", "1", "--out", str(out), "--probe", "0"]
    args += ["--daemon-env", "HIL_MEMPROBE_PERIOD_S=0.5"]
    assert hil_main(args) == 0
    result = json.loads((out / "soak.json").read_text())
    assert result["daemon_env"] == {"HIL_MEMPROBE_PERIOD_S": "0.5"}
    probe = result["probe"]
    assert probe["samples"] >= 4  # ≥ 2 s of start-up plus 3 s of run at 0.5 s
    assert probe["rss_anon"]["last"] > 0
    # glibc's heap: what is in use is at most what was taken from the kernel
    assert 0 < probe["heap_in_use"]["last"] <= probe["heap_from_os"]["last"]
    assert "traced" not in probe  # tracemalloc only with --probe N > 0


def test_probe_summary_fits_slopes_over_the_soak_window(tmp_path: Path) -> None:
    from hil.soak import summarize_probe

    rows = [
        {
            "t_s": t,
            "rss_anon_kib": 1024 * (100 + t / 3600.0),  # +1 MiB/h
            "rss_file_kib": 0,
            "mallinfo2": {
                "arena": 50 << 20,
                "hblkhd": 0,
                "uordblks": 40 << 20,
                "fordblks": 10 << 20,
            },
            "traced_bytes": 30 << 20,
            "numpy_bytes": 5 << 20,
            "gc_objects": 1000,
            "asyncio_tasks": 12,
            "top_growth": [{"site": "x.py:1", "size_diff_b": 10, "size_b": 20, "count_diff": 1}],
        }
        for t in range(0, 1000, 10)
    ]
    path = tmp_path / "probe.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    # the daemon started 2 s before its first estimate: the probe's clock is shifted by 2 s
    out = summarize_probe(path, 0.0, 2.0, {"rss_mib": {"slope_from_s": 500.0}})
    assert out["samples"] == len(rows)
    assert out["rss_anon"]["slope_per_hour"] == pytest.approx(1.0)
    assert out["heap_in_use"]["slope_per_hour"] == pytest.approx(0.0, abs=1e-9)
    assert out["heap_free"]["last"] == pytest.approx(10.0)
    assert out["asyncio_tasks"]["max_steady"] == 12
    assert out["top_growth_since_baseline"][0]["site"] == "x.py:1"
