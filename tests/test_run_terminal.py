"""``dffd run`` as a user at a terminal runs it: in a real pseudo-terminal, stopped by Ctrl-C.

Ctrl-C is the byte 0x03 typed into the terminal, so the line discipline sends SIGINT to the
terminal's foreground process group exactly as a keyboard does. The daemon runs under ``make``
(the README's ``make run``): make and dffd start in one process group, and make dies of a SIGINT
it receives itself, whatever dffd does, so this checks that dffd keeps Ctrl-C to itself, stops in
order and that make then exits 0. The embedded broker and the dashboard move to free ports.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port
from tests.pty_support import CTRL_C, type_at_cue

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make"),
]

# Interpreter start, imports, kernels from the cache, broker, camera init, first frames on a
# loaded 2-core machine: the README run path's own test allows 20 s for the broker alone.
READY_TIMEOUT_S = 40.0
# The daemon's shutdown is bounded by 10 s (dffd.daemon.app.SHUTDOWN_TIMEOUT_S).
EXIT_TIMEOUT_S = 15.0
READY = re.compile(rb"ready: camera initialised and frames flowing")


@pytest.mark.timeout(90)
def test_ctrl_c_under_make_run_stops_dffd_cleanly_and_make_exits_0(tmp_path: Path) -> None:
    makefile = tmp_path / "Makefile"
    makefile.write_text(f"run:\n\t{sys.executable} -m dffd run\n", encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DFFD_")}
    env.update(
        DFFD_MQTT__EMBEDDED_PORT=str(free_port()),
        DFFD_WEB__LISTEN=f"127.0.0.1:{free_port()}",
        DFFD_LOG__DIR=str(tmp_path / "log"),
        COLUMNS="120",
        LINES="50",
    )
    code, text = type_at_cue(
        ["make", "-s", "-f", str(makefile), "run"], tmp_path, env, READY, CTRL_C,
        READY_TIMEOUT_S, EXIT_TIMEOUT_S,
    )  # fmt: skip
    assert code == 0, text[-3000:]
    assert "dffd stopped cleanly on Ctrl-C (SIGINT)" in text, text[-3000:]
    assert "pan/tilt stopped" in text
    assert "Interrupt" not in text  # make's own "*** [run] Interrupt"
