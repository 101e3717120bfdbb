"""dffd calibrate's operator: the lab procedure without a terminal is refused before anything
starts; Ctrl-D or Ctrl-C at a prompt stops it at once, without a traceback, saying what had been
measured and that no lens file was written."""

from __future__ import annotations

import argparse
import asyncio
import os
import pty
import re
import select
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dffd import calibrate as calibrate_module
from dffd.calibrate import run
from dffd.calibrate_operator import InputEndedError, ask_operator, stopped_message
from dffd.calibrate_rigs import SimRig
from dffd.cli.arguments import configure_calibrate
from dffd.exitcodes import EXIT_INTERRUPTED, EXIT_USAGE
from tests.pty_support import CTRL_C, CTRL_D, type_at_cue

REPO = Path(__file__).resolve().parent.parent
LAB_EXAMPLE = REPO / "config" / "lab-evi-d100.toml"
# A fresh interpreter that checks its inputs and stops (no kernels): ~1-3 s on a loaded machine.
CLI_TIMEOUT_S = 60.0
# From exec to the first prompt: interpreter start, the kernels from the numba cache (a cold
# cache compiles them: 20-40 s), the simulated camera's initialisation, the first frames. ~2 s.
PROMPT_TIMEOUT_S = 90.0
# From the key at the prompt to the exit: the camera link and the video stream closed. ~0.5 s.
EXIT_TIMEOUT_S = 15.0
# The simulated camera prints its pty and video URL once it serves them (~0.5 s).
SIM_START_TIMEOUT_S = 30.0
PROMPT = b"then press Enter: "
OLD_TABLE = "an older table\n"


@pytest.mark.parametrize(
    ("stdin", "what"),
    [
        ("devnull", "/dev/null (as under systemd or with </dev/null)"),
        ("pipe", "a pipe"),
        ("closed", "closed"),
    ],
)
def test_the_lab_procedure_without_a_terminal_is_refused_before_anything_starts(
    tmp_path: Path, stdin: str, what: str
) -> None:
    """Under systemd, from a pipe (Enter queued in advance) or with stdin closed: exit 2 and
    one paragraph on what to do, before the kernels load and the camera is opened."""
    port, video = tmp_path / "visca0", tmp_path / "video0"
    port.touch()  # devices that exist: the refusal is the terminal's, not theirs
    video.touch()
    out = tmp_path / "lens.toml"
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(
        NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"),
        PYTHONPATH=str(REPO),
        DFFD_LENS__FILE=str(out),
        DFFD_CAMERA__PORT=str(port),
        DFFD_CAPTURE__DEVICE=str(video),
    )
    argv = ["calibrate", "--config", str(LAB_EXAMPLE), "--out", str(out)]
    probe = (
        ("import os; os.close(0)\n" if stdin == "closed" else "")
        + "import sys\nfrom dffd import cli\n"
        + f"rc = cli.main({argv!r})\n"
        + "print(rc, 'dffd.core.kernels' in sys.modules, 'numba' in sys.modules)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True,
        timeout=CLI_TIMEOUT_S, check=False,
        **({"input": "\n" * 30} if stdin == "pipe" else {"stdin": subprocess.DEVNULL}),
    )  # fmt: skip
    assert done.stdout.split() == [str(EXIT_USAGE), "False", "False"], done.stderr
    assert done.stderr == (
        "dffd calibrate: the lab procedure asks the operator to place the target at each of its "
        f"23 depths and press Enter, but stdin is {what}, not a terminal: nobody can answer, and "
        "answers queued in a pipe or a file would confirm placements nobody made; run it from an "
        "interactive terminal (over ssh: ssh -t HOST dffd calibrate …)\n"
    )
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.timeout(PROMPT_TIMEOUT_S + EXIT_TIMEOUT_S + SIM_START_TIMEOUT_S)
@pytest.mark.parametrize(
    ("key", "why"),
    [(CTRL_D, "the input ended at the prompt (Ctrl-D)"), (CTRL_C, "interrupted (Ctrl-C)")],
)
def test_ctrl_d_or_ctrl_c_at_the_lab_prompt_stops_cleanly(
    tmp_path: Path, sim_camera: tuple[str, str], key: bytes, why: str
) -> None:
    """`dffd calibrate --config` on the simulated camera over its pty and MJPEG video, in a real
    terminal; the operator answers the first prompt with Ctrl-D or Ctrl-C."""
    port, url = sim_camera
    config = tmp_path / "lab.toml"
    config.write_text(
        f'[camera]\ndriver = "visca"\nport = "{port}"\nmodel = "evi-d100"\n'
        f'[capture]\nsource = "stream"\nurl = "{url}"\nfps = 30.0\n',
        encoding="utf-8",
    )
    out = tmp_path / "lens.toml"
    out.write_text(OLD_TABLE, encoding="utf-8")
    argv = [sys.executable, "-m", "dffd", "calibrate", "--config", str(config)]
    code, printed = _answer_in_terminal([*argv, "--depths", "2,5", "--out", str(out)], key)
    assert code == EXIT_INTERRUPTED, printed
    assert (
        f"dffd calibrate: stopped at 2 m (depth 1 of 2), {why}: 0 of the 2 depths measured; "
        f"no lens file was written: --out {out} is as it was"
    ) in printed
    assert "Traceback" not in printed
    assert out.read_text(encoding="utf-8") == OLD_TABLE


@pytest.mark.parametrize(
    ("stop", "why"),
    [("ctrl-d", "the input ended at the prompt (Ctrl-D)"), ("ctrl-c", "interrupted (Ctrl-C)")],
)
def test_a_stop_after_a_depth_says_what_was_measured_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    stop: str,
    why: str,
) -> None:
    """The procedure stopped at the second placement, after the first depth's sweep: exit 130,
    the depth measured and that it is not kept, --out untouched."""
    monkeypatch.setattr("dffd.calibrate_procedure.FRAMES_PER_SETTING", 1)

    class StoppedAtTheSecondDepth(SimRig):
        async def place_target(self, z_m: float) -> None:
            if z_m == 5.0:
                if stop == "ctrl-d":
                    raise InputEndedError("the input ended at the prompt")
                signal.raise_signal(signal.SIGINT)  # asyncio.run cancels the waiting prompt
                await asyncio.get_running_loop().create_future()
            await super().place_target(z_m)

    monkeypatch.setattr(calibrate_module, "SimRig", StoppedAtTheSecondDepth)
    out = tmp_path / "lens.toml"
    out.write_text(OLD_TABLE, encoding="utf-8")
    parser = argparse.ArgumentParser()
    configure_calibrate(parser)
    args = parser.parse_args(["--sim", "--depths", "2,5,12", "--out", str(out)])
    # Ctrl-C's SIGINT as at a terminal (a shell script's background job inherits it ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert run(args) == EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGINT, previous)
    printed = capsys.readouterr()
    assert printed.err == (
        f"\ndffd calibrate: stopped at 5 m (depth 2 of 3), {why}: 1 of the 3 depths measured "
        "(2 m), not kept (a table is fitted from the sweeps of one whole run); no lens file was "
        f"written: --out {out} is as it was\n"
    )
    assert printed.out == ""  # no residuals, no table
    assert out.read_text(encoding="utf-8") == OLD_TABLE


def test_the_stop_message_counts_the_sweeps() -> None:
    depths = [1.0, 1.5, 2.0]
    assert stopped_message("x", depths, 2, None) == (
        "stopped at 2 m (depth 3 of 3), x: 2 of the 3 depths measured (1 to 1.5 m), not kept "
        "(a table is fitted from the sweeps of one whole run); no lens table was printed"
    )
    assert stopped_message("x", depths, 5, Path("t.toml")) == (
        "stopped after the last depth, x: all 3 depths measured and 2 swept again, not kept (a "
        "table is fitted from the sweeps of one whole run); no lens file was written: --out "
        "t.toml is as it was"
    )


async def test_the_prompt_takes_an_enter_typed_after_it_and_stops_at_ctrl_d_or_ctrl_c(
    capsys: pytest.CaptureFixture[str],
) -> None:
    loop = asyncio.get_running_loop()
    master, terminal = pty.openpty()
    try:
        os.write(master, b"\n")  # Enter pressed during the last sweep, before the prompt …
        assert select.select([terminal], [], [], EXIT_TIMEOUT_S)[0]  # … in the terminal's input
        loop.call_soon(os.write, master, CTRL_D)  # typed once the prompt waits
        with pytest.raises(InputEndedError):  # the early Enter did not confirm the placement
            await ask_operator("Place the target 2 m away, then press Enter: ", terminal)
        assert capsys.readouterr().out == "Place the target 2 m away, then press Enter: "
        loop.call_soon(os.write, master, b"placed\n")
        await ask_operator("again: ", terminal)
        # Ctrl-C: asyncio.run cancels the main task; the wait ends at once, nothing left reading
        waiting = asyncio.create_task(ask_operator("again: ", terminal))
        loop.call_soon(waiting.cancel)
        with pytest.raises(asyncio.CancelledError):
            await waiting
        assert not loop.remove_reader(terminal)
    finally:
        os.close(master)
        os.close(terminal)


# -- helpers ----------------------------------------------------------------------------------
@pytest.fixture
def sim_camera() -> Iterator[tuple[str, str]]:
    """`dffd sim-camera` on a pty, its frames as MJPEG over HTTP: (pty path, video URL)."""
    with subprocess.Popen(
        [sys.executable, "-m", "dffd", "sim-camera", "--no-pace", "--video", "http://127.0.0.1:0"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    ) as server:  # fmt: skip
        try:
            assert server.stdout is not None
            ready, _, _ = select.select([server.stdout], [], [], SIM_START_TIMEOUT_S)
            assert ready, "dffd sim-camera did not start"
            port, url = server.stdout.readline().strip(), server.stdout.readline().strip()
            assert url.startswith("http://"), (port, url)
            yield port, url
        finally:
            server.terminate()
            server.wait(timeout=EXIT_TIMEOUT_S)


def _answer_in_terminal(argv: list[str], key: bytes) -> tuple[int, str]:
    """Run ``argv`` on a new pty, type ``key`` at the first prompt; (exit code, output)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env["PYTHONPATH"] = str(REPO)
    prompt = re.compile(re.escape(PROMPT))
    return type_at_cue(argv, REPO, env, prompt, key, PROMPT_TIMEOUT_S, EXIT_TIMEOUT_S)
