"""Package data: the embedded defaults, lens tables and simulated worlds, found by name."""

from __future__ import annotations

from pathlib import Path

import pytest

from dffd.config import ConfigError, load_config
from dffd.resources import (
    ResourceNotFoundError,
    default_config_file,
    is_lens_name,
    lens_table,
    lens_table_names,
)
from drivers.sim.config import SimConfigError, WorldConfig
from drivers.sim.resources import reference_camera_file, world_file, world_names, world_tables
from hil.scenario import SCENARIO_NAMES, TargetSpec, TrajectorySpec, load_scenario

WORLDS = ("approach", "figure-eight", "line", "paper-circle", "random", "static", "stop-and-go")


def test_packaged_files_exist_and_are_listed() -> None:
    assert default_config_file().is_file()
    assert reference_camera_file().is_file()
    assert "sim-evi-d100" in lens_table_names()
    assert lens_table("sim-evi-d100").is_file()
    assert world_names() == WORLDS


def test_unknown_names_list_the_known_ones() -> None:
    with pytest.raises(ResourceNotFoundError, match=r"no packaged lens table 'nope'.*sim-evi-d100"):
        lens_table("nope")
    with pytest.raises(SimConfigError, match=r"no simulated world 'nope'; known worlds: approach"):
        world_file("nope")


def test_lens_name_or_path() -> None:
    assert is_lens_name("sim-evi-d100")
    assert not is_lens_name("sim-evi-d100.toml")
    assert not is_lens_name("lenses/mine")
    assert not is_lens_name(Path("/etc/dffd/lenses/x.toml"))


def test_config_lens_file_may_name_a_packaged_table(tmp_path: Path) -> None:
    path = tmp_path / "dffd.toml"
    path.write_text('[lens]\nfile = "sim-evi-d100"\n', encoding="utf-8")
    assert load_config(path).lens.file == lens_table("sim-evi-d100")
    path.write_text('[lens]\nfile = "evi-d70"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"lens\.file: no packaged lens table 'evi-d70'"):
        load_config(path)


@pytest.mark.parametrize("name", WORLDS)
def test_every_world_is_valid_for_the_simulator(name: str) -> None:
    tables = world_tables(name)
    world = WorldConfig.model_validate(tables)
    assert world.target.size_m == pytest.approx(0.03576)


def test_bench_scenarios_take_their_world_from_the_simulator() -> None:
    assert set(SCENARIO_NAMES) == set(WORLDS)
    for name in SCENARIO_NAMES:
        scenario = load_scenario(name)
        world = world_tables(name)
        assert scenario.world == name
        assert scenario.trajectory == TrajectorySpec.model_validate(world["trajectory"])
        # known_size_m is the scenario's own: what CF1 and the known-size baseline are told.
        told = {"known_size_m": 0.03576}
        assert scenario.target == TargetSpec.model_validate(world["target"] | told)


def test_world_file_errors(tmp_path: Path) -> None:
    bad = tmp_path / "w.toml"
    bad.write_text("[target]\nshape = 'disc'\n", encoding="utf-8")
    with pytest.raises(SimConfigError, match=r"needs a \[trajectory\] table"):
        world_tables(bad)
    with pytest.raises(SimConfigError, match="cannot read world file"):
        world_tables(tmp_path / "absent.toml")
