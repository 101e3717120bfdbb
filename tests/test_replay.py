"""``dffd replay`` on a synthetic recording, through the CLI dispatcher."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dffd.cli import main
from dffd.config import DffdConfig
from dffd.core.pipeline import Pipeline
from dffd.core.synthetic import DiscScene, closed_loop, synthetic_lens
from dffd.exitcodes import EXIT_FAILURE, EXIT_USAGE
from dffd.recording import RecordingWriter
from dffd.wiring import pipeline_config

LENS = synthetic_lens()
REPO = Path(__file__).resolve().parent.parent
# `dffd replay` of a missing recording: an interpreter start and the core's imports (~2-5 s on a
# loaded 2-core machine); a compile of the kernels would take 20-40 s more.
CLI_TIMEOUT_S = 60.0


def approach(t: float) -> tuple[float, float, float]:
    return 0.0, 0.0, 6.0 - 0.2 * t + 0.3 * math.sin(t)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "run"
    pipe = Pipeline(pipeline_config(DffdConfig()), LENS)  # the closed loop needs a planner
    with RecordingWriter(path, 30, (640, 480), LENS.to_meta()) as rec:
        for st in closed_loop(
            pipe, DiscScene(), LENS, approach, duration_s=8.0, seed=3, transit=True
        ):
            pipe.process(st.frame, st.tag)
            rec.write(st.frame, st.tag, (st.truth_m[2], st.truth_m[0], st.truth_m[1]))
    return path


def test_replay_writes_estimates_summary_and_plot(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, summ, png = tmp_path / "est.jsonl", tmp_path / "s.json", tmp_path / "p.png"
    code = main(
        [
            "replay",
            str(run_dir),
            "--out",
            str(out),
            "--summary",
            str(summ),
            "--plot",
            str(png),
            "--settle",
            "3",
        ]
    )
    assert code == 0
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert len(lines) > 50
    last = lines[-1]
    assert set(last["depth_m"]) == {"measured", "cf1", "cf2", "lpv", "kf", "smoothed"}
    # the offline smoother: at the last frame it is the filter; earlier it is never less sure
    assert last["depth_m"]["smoothed"] == pytest.approx(last["depth_m"]["kf"], abs=1e-9)
    mid = lines[len(lines) // 2]
    assert 0 < mid["sigma_m"]["smoothed"] <= mid["sigma_m"]["kf"] + 1e-12
    assert last["best"] == "lpv"
    assert last["depth_m"]["cf1"] is None  # no known size given
    assert last["r_px"] > 0
    assert last["size_m"] == pytest.approx(0.03576, rel=0.02)
    assert any(ln["depth_m"]["measured"] is not None for ln in lines)
    # The 3D tracker's fields: a track on the static target at the back-projected position.
    assert sum(last["model_probabilities"].values()) == pytest.approx(1.0)
    assert set(last["model_probabilities"]) == {"cv", "ca", "ct"}
    assert last["track_position_m"] == pytest.approx(last["position_world_m"], abs=0.05)
    assert all(s > 0 for s in last["position_sigma_m"])
    assert len(last["acceleration_m_s2"]) == len(last["track_velocity_m_s"]) == 3
    assert math.isfinite(last["angular_speed_rad_s"])
    summary = json.loads(summ.read_text())
    assert summary["schema"] == 1
    assert summary["settle_s"] == 3
    lpv = summary["estimators"]["lpv"]
    assert "smoothed" in summary["estimators"]
    assert set(lpv) == {
        "n", "bias_m", "std_m", "rms_m", "ss_std_m", "p95_abs_m",
        # is the published σ honest: 2σ coverage and NEES, whole run and steady state
        "n_sigma", "coverage_2sigma", "nees", "ss_coverage_2sigma", "ss_nees",
        "first_abs_err_m", "first_sigma_m",
    }  # fmt: skip
    assert lpv["n_sigma"] == lpv["n"]
    assert 0.0 <= lpv["coverage_2sigma"] <= 1.0
    assert lpv["nees"] > 0
    # every estimator's σ per line, keyed as depth_m; the best's with z_m
    assert set(last["sigma_m"]) == set(last["depth_m"])
    assert last["z_sigma_m"] == last["sigma_m"]["lpv"] > 0
    assert lpv["ss_std_m"] < 0.0377
    assert summary["bursts"]["accepted"] > 10
    assert png.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "lpv" in printed
    assert "bursts accepted" in printed


def test_replay_known_size_enables_cf1(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "est.jsonl"
    assert (
        main(["replay", str(run_dir), "--out", str(out), "--known-size", "0.03576", "--best", "kf"])
        == 0
    )
    last = json.loads(out.read_text().splitlines()[-1])
    assert last["depth_m"]["cf1"] is not None
    assert last["best"] == "kf"


def test_replay_errors_and_exit_codes(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(tmp_path / "nothing"), "--out", str(tmp_path / "e")]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["replay", str(run_dir), "--out", str(tmp_path / "e"), "--roi", "1,2"]) == 2
    with pytest.raises(SystemExit) as exc:
        main(["replay", str(run_dir)])  # --out missing: argparse usage error
    assert exc.value.code == 2


@pytest.mark.parametrize("option", ["--out", "--summary", "--plot"])
def test_an_output_that_cannot_be_written_is_refused_before_the_replay_as_calibrate_does(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str
) -> None:
    """A missing directory was a bare "[Errno 2] No such file or directory" after the whole
    replay, exit 1; now it is calibrate's message, before anything runs, exit 2."""
    missing, a_file = tmp_path / "missing", tmp_path / "a-file"
    a_file.write_text("", encoding="utf-8")
    cases = {
        missing / "x": (
            f"{missing} does not exist (replay does not create it): create the directory first "
            f"(mkdir -p {missing}) or give another {option}"
        ),
        a_file / "x": f"{a_file} is not a directory",
        tmp_path: f"{option} {tmp_path} is a directory: give the ",
    }
    good = {
        "--out": tmp_path / "e.jsonl",
        "--summary": tmp_path / "s.json",
        "--plot": tmp_path / "p.png",
    }
    for bad, expected in cases.items():
        argv = [arg for name, path in (good | {option: bad}).items() for arg in (name, str(path))]
        assert main(["replay", str(run_dir), *argv]) == EXIT_USAGE
        printed = capsys.readouterr()
        assert printed.out == ""  # nothing ran
        assert printed.err.startswith(f"dffd replay: {option} {bad}")
        assert expected in printed.err
        assert not any(path.exists() for path in good.values())  # nothing written


def test_replay_checks_its_inputs_before_loading_the_kernels(tmp_path: Path) -> None:
    # A fresh install (empty numba cache): a missing recording is reported at once, without
    # compiling the tracker's kernels first (~30 s) and without saying that it compiles them.
    cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "-m", "dffd", "replay", str(tmp_path / "nothing"), "--out", "e.jsonl"],
        env=env,
        capture_output=True,
        text=True,
        timeout=CLI_TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == EXIT_FAILURE
    assert "not found" in proc.stderr
    assert "compil" not in proc.stderr
    assert not cache.exists() or not any(cache.rglob("*.nbi"))


def test_replay_config_configures_the_core(run_dir: Path, tmp_path: Path) -> None:
    conf = tmp_path / "dffd.toml"
    conf.write_text('[estimators]\nbest = "cf2"\n', "utf-8")
    out = tmp_path / "est.jsonl"
    assert main(["replay", str(run_dir), "--out", str(out), "--config", str(conf)]) == 0
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert lines
    assert all(ln["best"] == "cf2" for ln in lines)


def test_replay_reports_a_bad_config(run_dir: Path, tmp_path: Path) -> None:
    conf = tmp_path / "dffd.toml"
    conf.write_text("[estimators]\nsigma_psi = -1\n", "utf-8")
    code = main(["replay", str(run_dir), "--out", str(tmp_path / "e.jsonl"), "--config", str(conf)])
    assert code == 2


def test_replay_counts_every_burst_without_a_depth_with_its_reason(run_dir: Path) -> None:
    """A burst that lost a frame is dropped before the fit: replay counts it as rejected, by
    reason (it used to be missing from the summary: 'rejected 0' with bursts dropped)."""
    from dffd.core.lens import Lens
    from dffd.recording import RecordingReader
    from dffd.replay import replay, summarize

    reader = RecordingReader(run_dir)
    lens = Lens.from_meta(reader.meta["lens"])
    config = pipeline_config(DffdConfig())
    # every third burst loses its middle frame (as when the capture drops it)
    frames = [
        (frame, tag)
        for frame, tag in reader
        if not (tag.burst is not None and tag.burst[1] == 1 and tag.burst[0] % 3 == 0)
    ]
    result = replay(frames, lens, config)
    dropped = result.reasons.get("dropped: 2 of 3 frames with a focus cost", 0)
    assert dropped >= 3
    assert result.rejected == sum(result.reasons.values())
    assert reader.truth is not None
    summary = summarize(
        result.lines, reader.truth, 3.0, 0.0, bursts=(result.accepted, result.rejected),
        reasons=result.reasons,
    )  # fmt: skip
    assert summary["bursts"]["reasons"]["dropped: 2 of 3 frames with a focus cost"] == dropped
