"""The simulator's package data: its reference camera and the worlds it can show.

``data/sim-camera.toml`` is the reference EVI-D100-like camera (every value carries its source);
``data/worlds/<name>.toml`` each hold the ``[target]`` and ``[trajectory]`` tables of one world
(keys as :class:`drivers.sim.config.TargetConfig` / :class:`~drivers.sim.config.TrajectoryConfig`).
The HIL bench's scenarios and the daemon's simulated camera both take their worlds from here.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from drivers.resources import ResourceNotFoundError, packaged_file, packaged_names
from drivers.sim.config import SimConfigError

__all__ = [
    "WORLD_SUFFIX",
    "reference_camera_file",
    "world_file",
    "world_names",
    "world_tables",
]

_PACKAGE = "drivers.sim"
_DATA = "data"
_WORLDS = "worlds"
WORLD_SUFFIX = ".toml"


def reference_camera_file() -> Path:
    """The reference simulated camera's TOML (``drivers/sim/data/sim-camera.toml``)."""
    return packaged_file(_PACKAGE, _DATA, "sim-camera.toml")


def world_names() -> tuple[str, ...]:
    """Names of the packaged worlds (``static``, ``approach``, ``paper-circle``, …), sorted."""
    return packaged_names(_PACKAGE, f"{_DATA}/{_WORLDS}", WORLD_SUFFIX)


def world_file(name: str) -> Path:
    """The packaged world ``name``'s TOML; SimConfigError naming the known worlds if absent."""
    try:
        return packaged_file(_PACKAGE, _DATA, _WORLDS, name + WORLD_SUFFIX)
    except ResourceNotFoundError:
        known = ", ".join(world_names())
        raise SimConfigError(f"no simulated world {name!r}; known worlds: {known}") from None


def world_tables(name_or_path: str | Path) -> dict[str, dict[str, Any]]:
    """The ``target`` and ``trajectory`` tables of a world, by packaged name or TOML path.

    Raises SimConfigError (unreadable, not TOML, or without a ``[trajectory]`` table).
    """
    path = Path(name_or_path)
    if path.suffix != WORLD_SUFFIX:
        path = world_file(str(name_or_path))
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SimConfigError(f"cannot read world file {path}: {exc.strerror}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SimConfigError(f"world file {path} is not valid TOML: {exc}") from exc
    target = data.get("target", {})
    trajectory = data.get("trajectory")
    if not isinstance(trajectory, dict) or not isinstance(target, dict):
        raise SimConfigError(
            f"world file {path} needs a [trajectory] table (and optionally [target]) with the "
            "keys of drivers/sim/config.py TrajectoryConfig/TargetConfig"
        )
    return {"target": target, "trajectory": trajectory}
