"""The package runs installed: the wheel, in a fresh venv outside the tree, from another directory.

The wheel is built (``python -m build --wheel``) from a copy of the tree, installed into a new
virtual environment under the test's tmp directory, and its console script runs with neither the
source tree on ``sys.path`` nor the tree as working directory: defaults, lens tables, simulated
worlds and schemas must come from package data.

The new venv has no system site-packages. The wheel goes in with ``--no-deps`` and the heavy
dependencies (NumPy, SciPy, OpenCV, numba, …) are made visible through one ``.pth`` line naming
the running interpreter's site-packages: a full ``pip install`` of them took 57 s on the 2-core
dev machine (from the local wheel cache), this takes ~8 s. That directory's own ``.pth`` files
(an editable install of dffd) are not processed for a path added this way, and the test checks
that ``dffd``, ``drivers`` and ``hil`` are imported from the new venv.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
from dataclasses import dataclass
from pathlib import Path

import aiomqtt
import pytest

from tests.conftest import Mosquitto

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
# Wheel build in an isolated environment (setuptools from the local index): ~4 s measured.
BUILD_TIMEOUT_S = 180.0
# venv creation (~6 s, it bootstraps pip) and the --no-deps install (~2 s).
INSTALL_TIMEOUT_S = 120.0
# `dffd run --duration 10` on a fresh install: ~17 s of start-up (the numba kernels compile, no
# cache yet) plus the 10 s run: 29 s measured; the bound allows for a loaded machine.
RUN_TIMEOUT_S = 120.0
# `dffd replay` of a 2 s recording and `dffd calibrate --sim` at two depths: 5-15 s each.
COMMAND_TIMEOUT_S = 90.0
# Per test: the module fixture's build and install count toward the first test that uses it.
TEST_TIMEOUT_S = 400
MIN_ESTIMATES = 10  # ~4 estimates/s once tracking; the first arrive within ~2 s of start
# The tools' caches by name (a "*cache*" pattern also dropped dffd/core/kernel_cache.py).
_SKIP_COPY = shutil.ignore_patterns(
    ".git", ".venv", ".*_cache", "__pycache__", "*.egg-info", "build", "dist", "out", "runs"
)


@dataclass(frozen=True)
class Installed:
    """A venv with the wheel installed, and an empty working directory outside the tree."""

    venv: Path
    cwd: Path

    @property
    def bin(self) -> Path:
        return self.venv / "bin"

    def env(self, **extra: str) -> dict[str, str]:
        """The environment of a user's shell: no PYTHONPATH, no DFFD_ overrides."""
        env = {
            k: v
            for k, v in os.environ.items()
            if k != "PYTHONPATH" and not k.upper().startswith("DFFD_")
        }
        env["NUMBA_CACHE_DIR"] = str(self.venv / "numba-cache")
        return env | extra

    def run(
        self, *args: str, timeout: float = COMMAND_TIMEOUT_S
    ) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [str(self.bin / args[0]), *args[1:]],
            cwd=self.cwd, env=self.env(), capture_output=True, text=True, timeout=timeout,
            check=False,
        )  # fmt: skip


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    root = tmp_path_factory.mktemp("wheel")
    src, dist, env_dir, cwd = root / "src", root / "dist", root / "venv", root / "elsewhere"
    shutil.copytree(REPO, src, ignore=_SKIP_COPY)
    _check(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(dist), str(src)],
        BUILD_TIMEOUT_S,
    )
    (wheel,) = dist.glob("dffd-*.whl")
    venv.create(env_dir, system_site_packages=False, with_pip=True)
    purelib = Path(_venv_path(env_dir, "purelib"))
    deps = {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}
    (purelib / "_dffd_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    _check(
        [str(env_dir / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index",
         "--quiet", str(wheel)],
        INSTALL_TIMEOUT_S,
    )  # fmt: skip
    cwd.mkdir()
    return Installed(env_dir, cwd)


@pytest.mark.timeout(TEST_TIMEOUT_S)
def test_the_installed_copy_is_used_with_its_package_data(installed: Installed) -> None:
    probe = installed.run(
        "python",
        "-c",
        "import json, dffd, drivers, hil\n"
        "from dffd.resources import default_config_file, lens_table_names\n"
        "from drivers.sim.resources import reference_camera_file, world_names\n"
        "from hil.scenario import available_scenarios\n"
        "print(json.dumps({'modules': [dffd.__file__, drivers.__file__, hil.__file__],\n"
        "  'config': str(default_config_file()), 'camera': str(reference_camera_file()),\n"
        "  'lenses': lens_table_names(), 'worlds': world_names(),\n"
        "  'scenarios': available_scenarios()}))",
    )
    assert probe.returncode == 0, probe.stderr
    found = json.loads(probe.stdout)
    prefix = str(installed.venv)
    assert all(path.startswith(prefix) for path in found["modules"]), found["modules"]
    assert found["config"].startswith(prefix)
    assert found["camera"].startswith(prefix)
    assert "sim-evi-d100" in found["lenses"]
    names = {"static", "approach", "paper-circle", "figure-eight", "random"}
    assert names <= set(found["worlds"])
    assert names <= set(found["scenarios"])
    check = installed.run("dffd", "check-config", "--check-files", str(found["config"]))
    assert check.returncode == 0, check.stderr


@pytest.mark.timeout(TEST_TIMEOUT_S)
async def test_dffd_run_publishes_estimates(installed: Installed, mosquitto: Mosquitto) -> None:
    estimates: list[dict[str, object]] = []
    async with aiomqtt.Client(mosquitto.host, mosquitto.port) as client:
        await client.subscribe("dffd/sim/estimate")
        env = installed.env(DFFD_MQTT__URL=mosquitto.url, DFFD_LOG__DIR=str(installed.cwd / "log"))
        log = installed.cwd / "run.log"
        with log.open("wb") as out:
            proc = await asyncio.create_subprocess_exec(
                str(installed.bin / "dffd"), "run", "--duration", "10", "--no-console",
                cwd=installed.cwd, env=env, stdout=out, stderr=out,
            )  # fmt: skip
        collector = asyncio.create_task(_collect(client, estimates))
        try:
            async with asyncio.timeout(RUN_TIMEOUT_S):
                code = await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            collector.cancel()
    text = log.read_text(errors="replace")
    assert code == 0, text[-3000:]
    assert len(estimates) >= MIN_ESTIMATES, text[-3000:]
    assert any(isinstance(e.get("z_m"), float) for e in estimates)


@pytest.mark.timeout(TEST_TIMEOUT_S)
def test_dffd_replay_and_calibrate_run_installed(installed: Installed, tmp_path: Path) -> None:
    recording = _tiny_recording(tmp_path / "rec")
    out = tmp_path / "est.jsonl"
    replay = installed.run("dffd", "replay", str(recording), "--out", str(out))
    assert replay.returncode == 0, replay.stderr
    assert len(out.read_text().splitlines()) > 20
    lens = tmp_path / "lens.toml"
    calibrate = installed.run("dffd", "calibrate", "--sim", "--depths", "2,6", "--out", str(lens))
    assert calibrate.returncode == 0, calibrate.stderr
    assert "focus_table" in lens.read_text()


def _tiny_recording(path: Path) -> Path:
    """A 2 s synthetic recording (the format is the contract; written by the tree's code)."""
    from dffd.config import DffdConfig
    from dffd.core.pipeline import Pipeline
    from dffd.core.synthetic import DiscScene, closed_loop, synthetic_lens
    from dffd.recording import RecordingWriter
    from dffd.wiring import pipeline_config

    lens = synthetic_lens()
    pipe = Pipeline(pipeline_config(DffdConfig()), lens)
    with RecordingWriter(path, 30, (640, 480), lens.to_meta()) as rec:
        for st in closed_loop(
            pipe, DiscScene(), lens, lambda t: (0.0, 0.0, 5.0), duration_s=2.0, seed=1
        ):
            pipe.process(st.frame, st.tag)
            rec.write(st.frame, st.tag, (st.truth_m[2], st.truth_m[0], st.truth_m[1]))
    return path


async def _collect(client: aiomqtt.Client, into: list[dict[str, object]]) -> None:
    async for message in client.messages:
        assert isinstance(message.payload, bytes)
        into.append(json.loads(message.payload))


def _check(cmd: list[str], timeout: float) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    assert proc.returncode == 0, f"{' '.join(cmd)}:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"


def _venv_path(env_dir: Path, name: str) -> str:
    return sysconfig.get_path(name, vars={"base": str(env_dir), "platbase": str(env_dir)})
