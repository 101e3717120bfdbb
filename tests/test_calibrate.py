"""dffd calibrate against the simulated camera: focus table vs the simulator's ground truth."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from dffd import calibrate as calibrate_module
from dffd.calibrate import run
from dffd.calibrate_fit import lens_from_points
from dffd.calibrate_lensfile import write_lens_file
from dffd.calibrate_parabola import vertex
from dffd.calibrate_procedure import calibrate, calibrate_table, measure_latency, sharpest
from dffd.calibrate_rigs import LabRig, SimRig
from dffd.calibrate_types import CalibrationError, DepthPoint
from dffd.cli.arguments import configure_calibrate
from dffd.config import check_run_config, load_config
from dffd.core.lens import Lens
from dffd.exitcodes import EXIT_FAILURE, EXIT_USAGE
from dffd.resources import lens_table
from drivers.sim.resources import reference_camera_file

REPO = Path(__file__).resolve().parent.parent
LAB_EXAMPLE = REPO / "config" / "lab-evi-d100.toml"
TRUTH = Lens.from_toml(lens_table("sim-evi-d100"))
# `dffd calibrate` refusing its arguments in a fresh interpreter: the start and the imports of
# the core (no kernels), ~1-3 s on the 2-core machine under load.
CLI_TIMEOUT_S = 60.0
# Measured bias of the sweep on the reference simulator: the sharpest counts come out 15–80
# counts on the far side of the true table (≤ 2% in depth at 10 m). 120 counts bounds it.
COUNTS_TOL = 120


def test_vertex_of_a_parabola() -> None:
    import numpy as np

    x = np.arange(0.0, 20.0)
    assert vertex(x, (x - 7.3) ** 2 + 1.0) == pytest.approx(7.3, abs=1e-6)


def test_non_monotone_points_are_refused() -> None:
    points = [
        DepthPoint(2.0, 100, 31.5, 1.0),
        DepthPoint(4.0, 200, 31.4, 1.0),
        DepthPoint(3.0, 300, 31.6, 1.0),
    ]
    with pytest.raises(CalibrationError, match="monotone"):
        lens_from_points("x", 31.0, 0.005, points)


async def test_sim_sweep_matches_the_ground_truth_and_latency() -> None:
    rig = SimRig(reference_camera_file())
    for z in (1.5, 4.0, 10.0):
        await rig.place_target(z)
        point = await sharpest(rig, z, settle_frames=3)
        assert abs(point.counts - TRUTH.counts_for_depth(z)) <= COUNTS_TOL, (z, point)
        assert point.v_mm == pytest.approx(TRUTH.v_from_depth(z))
    await rig.place_target(3.0)
    assert await measure_latency(rig) == round(rig.config.capture.capture_latency_frames)


async def test_the_procedure_places_the_target_at_each_depth_in_order() -> None:
    """The lab and --sim share calibrate(); the rig is asked for each depth, latency first."""
    placed: list[float] = []

    class Recording(SimRig):
        async def place_target(self, z_m: float) -> None:
            placed.append(z_m)
            await super().place_target(z_m)

    points, latency = await calibrate(Recording(reference_camera_file()), [2.0, 6.0])
    assert placed == [2.0, 6.0]
    assert [p.z_m for p in points] == [2.0, 6.0]
    assert points[0].counts > points[1].counts  # nearer = more counts (towards 0x8400)
    assert latency == 1


def test_cli_writes_a_loadable_lens_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from dffd.cli import loading

    monkeypatch.setattr(loading, "kernels_warm", lambda: False)  # as on a first start
    parser = _parser()
    out = tmp_path / "lens.toml"
    (tmp_path / "lens.toml").write_text("an older table\n", encoding="utf-8")
    args = parser.parse_args(["--sim", "--depths", "2,5,12", "--out", str(out)])
    assert run(args) == 0
    # the inputs were good: it said it compiles the kernels, once
    assert capsys.readouterr().err.count("compiling the tracker's kernels") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lens.toml"]  # no temporary file left
    lens = Lens.from_toml(out)
    assert len(lens.focus_counts) == 3
    assert lens.depth_from_v(lens.v_from_counts(TRUTH.counts_for_depth(5.0))) == pytest.approx(
        5.0, rel=0.03
    )
    assert run(parser.parse_args(["--depths", "2,5"])) == 2  # neither --sim nor --config


# The default procedure's 23 depths take ~30 s here (one frame a setting) and up to 3x that when
# the machine is shared; the module default (60 s) would fail it on load alone.
@pytest.mark.timeout(240)
def test_sim_runs_with_its_own_defaults(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # `dffd calibrate --sim` with no --depths: the standard set, moved out where the simulated
    # 35.76 mm target is larger than the tracker takes (1.0 m: 222 px in radius). One frame a
    # setting instead of four keeps the test short (~40 s with the defaults).
    monkeypatch.setattr("dffd.calibrate_procedure.FRAMES_PER_SETTING", 1)
    parser = argparse.ArgumentParser()
    configure_calibrate(parser)
    out = tmp_path / "lens.toml"
    assert run(parser.parse_args(["--sim", "--out", str(out)])) == 0
    printed = capsys.readouterr().out
    assert (
        "depths: 1.2, 1.5, 2, 2.25, 2.5, 2.75, 3, 3.25, 3.5, 4, 4.5, 5, 5.5, 6.25, 7, 7.75, 8.5, "
        "9.25, 10, 12, 14, 17, 20 m"
    ) in printed
    # where each depth's sweep is read, and the model's residuals at its bracket's two ends
    # (the depths whose bracket meets infinity focus, ~11 m on, are not fitted), and overall
    assert printed.count("read at counts") == 23
    assert printed.count("residual at v") >= 2 * 10
    assert "not fitted (the bracket meets the end of the focus range)" in printed
    assert "focus model: P(counts) polynomial of degree" in printed
    # and the table's own uncertainty per depth
    assert printed.count("table ± ") == 23
    assert "table uncertainty (1σ)" in printed
    lens = Lens.from_toml(out)
    assert lens.f_number == pytest.approx(2.9)  # the rig's, for the estimator's burst plan
    # the table states its own standard error, below the fit's residual (p/n of its variance)
    assert 0 < lens.table_sigma_v_mm < 2e-3
    # and per calibrated depth (each fitted depth's own leave-one-out), read back from the file
    assert len(lens.table_sigma_v_at) >= 10
    assert all(s >= 0 for _, s in lens.table_sigma_v_at)
    assert any(s > 0 for _, s in lens.table_sigma_v_at)
    # a smooth model tabulated densely over the calibrated range, within 1 % of the truth
    assert len(lens.focus_counts) > 50
    for z in (1.5, 3.0, 7.0, 12.0):
        got = lens.depth_from_v(lens.v_from_counts(TRUTH.counts_for_depth(z)))
        assert got == pytest.approx(z, rel=0.01)


# Eight sweeps of ~80 frames (one frame a setting): ~10 s here, several times that when shared.
@pytest.mark.timeout(180)
async def test_a_misplaced_depth_is_swept_again_and_the_table_recovers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The operator first puts the target 0.3 m too far at 4.5 m: the other depths predict that
    sweep badly, the procedure asks for 4.5 m again; the two sweeps disagree, a third decides,
    and the table is right there."""
    monkeypatch.setattr("dffd.calibrate_procedure.FRAMES_PER_SETTING", 1)
    placed: list[float] = []

    class Misplaced(SimRig):
        async def place_target(self, z_m: float) -> None:
            first = z_m == 4.5 and z_m not in placed
            placed.append(z_m)
            await super().place_target(4.8 if first else z_m)

    depths = [2.0, 3.0, 4.5, 7.0, 10.0, 14.0]
    result = await calibrate_table(Misplaced(reference_camera_file()), depths)
    assert placed[: len(depths)] == depths
    assert placed.count(4.5) == 3
    # another depth may be asked for once while 4.5 m still bends the fit (one frame a setting:
    # the readings' σ is small against a misplaced neighbour's pull), never more
    assert all(placed.count(z) <= 2 for z in depths if z != 4.5)
    assert result.repeated.count(4.5) == 2
    assert result.check is not None
    assert result.check.repeat == ()
    at_45 = next(d for d in result.check.depths if d.z_m == 4.5)
    assert at_45.n_sweeps == 3
    lens = result.table.lens
    got = lens.depth_from_v(lens.v_from_counts(TRUTH.counts_for_depth(4.5)))
    assert got == pytest.approx(4.5, rel=0.01)  # the 0.3 m misplacement is outvoted
    assert any("swept again" in line for line in result.lines())


async def test_a_target_too_large_for_the_tracker_is_named_as_such() -> None:
    rig = SimRig(reference_camera_file())
    await rig.place_target(1.0)
    with pytest.raises(CalibrationError, match="larger than the tracker takes"):
        await sharpest(rig, 1.0, settle_frames=3)


def test_sim_depths_where_the_target_does_not_fit_are_refused_up_front(
    capsys: pytest.CaptureFixture[str],
) -> None:
    parser = argparse.ArgumentParser()
    configure_calibrate(parser)
    assert run(parser.parse_args(["--sim", "--depths", "1,3"])) == 2  # refused up front
    assert "at 1 m the simulated 35.76 mm target is 222 px in radius" in capsys.readouterr().err


def test_lab_mode_needs_a_visca_camera_and_a_video_device(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    configure_calibrate(parser)
    sim_only = tmp_path / "sim.toml"
    sim_only.write_text("[camera]\ndriver = 'sim'\n", encoding="utf-8")
    assert run(parser.parse_args(["--config", str(sim_only), "--depths", "2,5"])) == 2
    assert "camera.driver = 'visca'" in capsys.readouterr().err
    lab = tmp_path / "lab.toml"
    lab.write_text(
        "[camera]\ndriver = 'visca'\nport = '/dev/null-visca'\n"
        "[capture]\nsource = 'v4l2'\ndevice = '/dev/null-video'\n",
        encoding="utf-8",
    )
    rig = LabRig(load_config(lab))
    assert rig.focus_range == (0x1000, 0x8400)  # EVI-D100 profile
    assert rig.focal_length_mm == TRUTH.focal_length_mm  # reused from lens.file


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    configure_calibrate(parser)
    return parser


@pytest.mark.parametrize(
    ("out", "expected"),
    [
        ("missing/dir/lens.toml", "does not exist (calibrate does not create it)"),
        ("a-file/lens.toml", "is not a directory"),
        ("", "is a directory: give the lens file's path"),
    ],
)
def test_an_out_that_cannot_be_written_is_refused_before_the_procedure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], out: str, expected: str
) -> None:
    (tmp_path / "a-file").write_text("", encoding="utf-8")
    path = tmp_path / out
    assert run(_parser().parse_args(["--sim", "--depths", "2,5,12", "--out", str(path)])) == 2
    printed = capsys.readouterr()
    assert printed.out == ""  # nothing ran: no depths, no table
    assert f"dffd calibrate: --out {path}" in printed.err
    assert expected in printed.err
    if out.startswith("missing"):
        assert f"mkdir -p {path.parent}" in printed.err  # and how to fix it


# Three sweeps of ~80 frames (one frame a setting): a few seconds, several times that if shared.
@pytest.mark.timeout(180)
def test_a_table_that_cannot_be_written_at_the_end_is_printed_not_lost(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The directory checked at the start is gone when the table is written (a removed or
    unmounted directory): exit 1, the reason, and the table on stdout, no traceback."""
    monkeypatch.setattr("dffd.calibrate_procedure.FRAMES_PER_SETTING", 1)
    procedure = calibrate_module.calibrate_table
    directory = tmp_path / "lenses"
    directory.mkdir()
    out = directory / "lens.toml"

    async def then_the_directory_goes(*args: Any, **kwargs: Any) -> Any:
        result = await procedure(*args, **kwargs)
        shutil.rmtree(directory)
        return result

    monkeypatch.setattr(calibrate_module, "calibrate_table", then_the_directory_goes)
    assert (
        run(_parser().parse_args(["--sim", "--depths", "2,5,12", "--out", str(out)]))
        == EXIT_FAILURE
    )
    printed = capsys.readouterr()
    assert f"dffd calibrate: cannot write the lens table to --out {out}: " in printed.err
    assert "printed on stdout" in printed.err
    assert "Traceback" not in printed.err
    table = printed.out[printed.out.index("[lens]") :]
    lens = Lens.from_meta(tomllib.loads(table)["lens"], source="stdout")
    assert len(lens.focus_counts) == 3


def test_the_lens_file_is_replaced_whole_or_not_at_all(tmp_path: Path) -> None:
    out = tmp_path / "lens.toml"
    out.write_text("old\n", encoding="utf-8")
    out.chmod(0o640)
    write_lens_file(out, "new\n")
    assert out.read_text(encoding="utf-8") == "new\n"
    assert out.stat().st_mode & 0o777 == 0o640  # an existing table's mode is kept
    # through a symlink: the file it points to is replaced, the link stays
    link = tmp_path / "current.toml"
    link.symlink_to(out)
    write_lens_file(link, "newer\n")
    assert link.is_symlink()
    assert out.read_text(encoding="utf-8") == "newer\n"
    # a write that fails leaves nothing behind: no partial file, no temporary file
    blocked = tmp_path / "blocked.toml"
    (blocked / "inside").mkdir(parents=True)  # a non-empty directory: the rename fails
    with pytest.raises(OSError, match=r"blocked\.toml"):
        write_lens_file(blocked, "table\n")
    with pytest.raises(FileNotFoundError):
        write_lens_file(tmp_path / "gone" / "lens.toml", "table\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "blocked.toml",
        "current.toml",
        "lens.toml",
    ]


def test_the_lab_procedure_starts_without_the_lens_file_it_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The lab example's lens.file is the table calibrate writes: calibrate starts from the
    packaged lens's optics with a note; `dffd run` still refuses the missing file."""
    lens_file = tmp_path / "lenses" / "evi-d100-tele.toml"  # as /etc/dffd/lenses/… before it
    monkeypatch.setenv("DFFD_LENS__FILE", str(lens_file))
    config = load_config(LAB_EXAMPLE)
    rig = LabRig(config)
    assert rig.focal_length_mm == TRUTH.focal_length_mm  # the packaged sim-evi-d100's
    assert rig.pixel_pitch_mm == TRUTH.pixel_pitch_mm
    assert rig.f_number == TRUTH.f_number
    assert rig.zoom_counts == 16384  # the example's [lens] zoom_counts
    assert rig.optics_note is not None
    assert f"lens.file {lens_file} does not exist yet" in rig.optics_note
    assert "sim-evi-d100" in rig.optics_note
    # through the command line: past the lens file, stopped at the devices absent here, at once
    monkeypatch.setenv("DFFD_CAMERA__PORT", str(tmp_path / "no-visca"))
    monkeypatch.setenv("DFFD_CAPTURE__DEVICE", str(tmp_path / "no-video"))
    args = ["--config", str(LAB_EXAMPLE), "--out", str(lens_file)]
    lens_file.parent.mkdir()
    assert run(_parser().parse_args(args)) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "cannot read lens file" not in err
    assert f"camera.port: {tmp_path / 'no-visca'} does not exist" in err
    assert f"capture.device: {tmp_path / 'no-video'} does not exist" in err
    # dffd run and check-config keep requiring it
    refused = check_run_config(LAB_EXAMPLE)
    assert isinstance(refused, str)
    assert f"lens.file: {lens_file} does not exist" in refused


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--config", "{bad}", "--out", "{tmp}/lens.toml"], "did you mean 'burst_every_n_frames'?"),
        (["--sim", "--out", "{tmp}/missing/lens.toml"], "--out {tmp}/missing/lens.toml: "),
        (["--config", "{lab}", "--out", "{tmp}/lens.toml"], "camera.port: {tmp}/no-visca"),
    ],
)
def test_calibrate_checks_its_inputs_before_loading_the_kernels(
    tmp_path: Path, argv: list[str], expected: str
) -> None:
    """A fresh install (empty numba cache): a bad config, --out or device is reported at once,
    without compiling the tracker's kernels first (~30 s) or saying that it compiles them."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[scheduler]\nburst_every_n_frame = 2\n", encoding="utf-8")
    names = {"bad": str(bad), "tmp": str(tmp_path), "lab": str(LAB_EXAMPLE)}
    cache = tmp_path / "numba-cache"
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(
        NUMBA_CACHE_DIR=str(cache),
        PYTHONPATH=str(REPO),
        DFFD_LENS__FILE=str(tmp_path / "lens.toml"),
        DFFD_CAMERA__PORT=str(tmp_path / "no-visca"),
        DFFD_CAPTURE__DEVICE=str(tmp_path / "no-video"),
    )
    probe = (
        "import sys; from dffd import cli; "
        f"rc = cli.main(['calibrate', *{[a.format(**names) for a in argv]!r}]); "
        "print(rc, 'dffd.core.kernels' in sys.modules, 'numba' in sys.modules)"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True,
        timeout=CLI_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert done.stdout.split() == [str(EXIT_USAGE), "False", "False"], done.stderr
    assert expected.format(**names) in done.stderr
    assert "compil" not in done.stderr
    assert not cache.exists() or not any(cache.rglob("*.nbi"))
