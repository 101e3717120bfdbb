"""The lens file ``dffd calibrate`` writes: its text and the write.

:func:`lens_toml` is the lens TOML format (as ``dffd/defaults/lenses/*.toml``, read by
:class:`dffd.core.lens.Lens`) with the fit's lines as comments; :func:`write_lens_file` replaces
the file whole or not at all. Whether ``--out`` can take it is checked before the procedure
(minutes; ~1 a depth in the lab) by :func:`dffd.cli.output_path.output_problem`, which ``dffd
replay`` asks too.

Split from :mod:`dffd.calibrate` (the command).
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path

from dffd.core.lens import Lens, VertexResponse


def lens_toml(
    lens: Lens, zoom_counts: int | None, latency_frames: int, notes: list[str] | None = None
) -> str:
    """The lens calibration file (lens TOML format, as ``dffd/defaults/lenses/*.toml``);
    ``notes`` become comment lines (the fit's residuals)."""
    rows = "\n".join(
        f"    [{c}, {v:.7f}]," for c, v in zip(lens.focus_counts, lens.focus_v_mm, strict=True)
    )
    zoom = f"zoom_counts = {zoom_counts}\n" if zoom_counts is not None else ""
    f_number = f"f_number = {lens.f_number!r}\n" if lens.f_number is not None else ""
    if lens.table_sigma_v_mm > 0:  # the table's own standard error (docs/estimation.md §14)
        f_number += f"table_sigma_v_mm = {lens.table_sigma_v_mm:.3e}\n"
    if lens.table_sigma_v_at:  # and per calibrated depth (§25)
        sigma_rows = ", ".join(f"[{c}, {s:.3e}]" for c, s in lens.table_sigma_v_at)
        f_number += f"table_sigma_v_at = [{sigma_rows}]\n"
    comments = "".join(f"# {line}\n" for line in notes or [])
    response = _response_toml(lens.vertex_response) if lens.vertex_response is not None else ""
    return (
        "# Focus calibration written by `dffd calibrate` (docs/design.md §3).\n"
        f"# Measured capture latency: {latency_frames} frame(s) -> [capture] latency_frames.\n"
        f"{comments}"
        "[lens]\n"
        f'name = "{lens.name}"\n'
        f"focal_length_mm = {lens.focal_length_mm}\n"
        f"pixel_pitch_mm = {lens.pixel_pitch_mm}\n"
        f"{f_number}"
        f"{zoom}"
        f"focus_table = [\n{rows}\n]\n"
        f"{response}"
    )


def write_lens_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all: into a temporary file in the same
    directory, renamed over ``path`` (an existing file keeps its mode); OSError if it fails."""
    target = path.resolve()  # replace the file a symlink points to, not the symlink
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    created = False
    try:
        # 0o666 less the umask, as a plain write would create it
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        created = True
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        with contextlib.suppress(FileNotFoundError):
            tmp.chmod(stat.S_IMODE(target.stat().st_mode))
        tmp.replace(target)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                tmp.unlink()
        raise


# -- private helpers --------------------------------------------------------------------------
def _response_toml(response: VertexResponse) -> str:
    """The ``[lens.vertex_response]`` table (docs/estimation.md §21)."""

    def floats(values: tuple[float, ...]) -> str:
        return "[" + ", ".join(f"{x:.6g}" for x in values) + "]"

    return (
        "\n# The burst fit's vertex (fitted_h) against the true offset (true_h), in half-\n"
        "# brackets, measured on the sweeps above; the estimator inverts it (estimation §21).\n"
        "[lens.vertex_response]\n"
        f'measure = "{response.measure}"\n'
        f"half_width_rel = {response.half_width_rel:.6e}\n"
        f"depth_spread_h = {response.depth_spread_h:.6g}\n"
        f"n_depths = {response.n_depths}\n"
        f"true_h = {floats(response.true_h)}\n"
        f"fitted_h = {floats(response.fitted_h)}\n"
    )


__all__ = ["lens_toml", "write_lens_file"]
