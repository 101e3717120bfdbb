"""Loading: TOML file + ``DFFD_<SECTION>__<KEY>`` environment -> a validated ``DffdConfig``.

Relative paths written in a config file are resolved against that file's directory; relative
paths from the environment against the working directory. ``[lens] file`` may also name a lens
table shipped in the package (``sim-evi-d100``) and ``[sim] scenario`` a world shipped with the
simulator (``paper-circle``): see :mod:`dffd.resources` and :mod:`drivers.sim.resources`. All
paths are absolute after loading. Without a file, the embedded default
(``dffd/defaults/dffd.toml``, package data) is loaded.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from dffd.config.explain import ConfigError, describe_errors, env_name, environ_upper
from dffd.config.models import DffdConfig, SimSection
from dffd.resources import default_config_file
from drivers.sim.resources import world_names

__all__ = ["load_config"]


def load_config(path: Path | None = None) -> DffdConfig:
    """Load ``path`` (None: the embedded default) plus ``DFFD_…`` environment overrides.

    Raises ConfigError naming every bad field by its dotted path and saying what is allowed.
    """
    source = str(path) if path is not None else "embedded default configuration"
    file = path if path is not None else default_config_file()
    data = _read_toml(file)
    try:
        config = DffdConfig(**data)
    except ValidationError as exc:
        raise ConfigError(list(describe_errors(exc, data, DffdConfig)), source) from None
    return _resolve_paths(config, data, file.resolve().parent)


_PATH_FIELDS: tuple[tuple[str, str], ...] = (
    ("lens", "file"),
    ("mqtt", "password_file"),
    ("mqtt", "ca_file"),
    ("mqtt", "certfile"),
    ("mqtt", "keyfile"),
    ("log", "dir"),
    ("sim", "camera_config"),
    ("web", "token_file"),
)


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(
            [f"cannot read {path}: {exc.strerror}; check the path"],
            str(path),
        ) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            [f"not valid TOML: {exc} (a TOML file must be UTF-8 text; re-save it as UTF-8)"],
            str(path),
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"not valid TOML: {exc}"], str(path)) from None


def _resolve_paths(config: DffdConfig, data: Mapping[str, Any], base: Path) -> DffdConfig:
    """Make every path absolute: file values against ``base``, env/defaults against the cwd."""
    updates: dict[str, BaseModel] = {}
    for section, key in _PATH_FIELDS:
        model: BaseModel = updates.get(section) or getattr(config, section)
        value = getattr(model, key)
        if value is None:
            continue
        value = Path(value).expanduser()
        if not value.is_absolute():
            from_file = isinstance(data.get(section), dict) and key in data[section]
            from_env = env_name(section, key) in environ_upper()
            anchor = base if from_file and not from_env else Path.cwd()
            value = anchor / value
        updates[section] = model.model_copy(update={key: value})
    sim: SimSection = updates.get("sim") or config.sim  # type: ignore[assignment]
    if sim.scenario not in world_names() and not Path(sim.scenario).is_absolute():
        from_file = isinstance(data.get("sim"), dict) and "scenario" in data["sim"]
        from_env = env_name("sim", "scenario") in environ_upper()
        anchor = base if from_file and not from_env else Path.cwd()
        resolved = str(anchor / Path(sim.scenario).expanduser())
        updates["sim"] = sim.model_copy(update={"scenario": resolved})
    return config.model_copy(update=updates)
