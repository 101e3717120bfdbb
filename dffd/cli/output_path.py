"""Whether a file a subcommand writes (``--out``, ``--summary``, …) can be written, asked before
its work: ``dffd calibrate``'s procedure takes minutes, ``dffd replay``'s kernels and frames
seconds, and an error at the end would say only ``[Errno 2] …``."""

from __future__ import annotations

import tempfile
from pathlib import Path

__all__ = ["output_problem"]


def output_problem(path: Path, *, option: str, command: str, what: str, example: str) -> str | None:
    """Why ``command`` could not write its ``what`` (e.g. "lens file") to ``path``, given as
    ``option``, and what to do; None if it can. ``example`` is a file name for the advice when
    ``path`` is a directory. The directory is never created."""
    target = path.resolve()  # a symlink's file is written where it points
    directory = target.parent
    if target.is_dir():
        return (
            f"{option} {path} is a directory: give the {what}'s path, e.g. "
            f"{option} {path / example}"
        )
    if not directory.is_dir():
        state = "is not a directory" if directory.exists() else "does not exist"
        return (
            f"{option} {path}: {directory} {state} ({command} does not create it): create the "
            f"directory first (mkdir -p {directory}) or give another {option}"
        )
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        return (
            f"{option} {path}: cannot write in {directory} ({exc.strerror or exc}): run as a user "
            f"who may write there, or give another {option}"
        )
    return None
