"""The error explainer: pydantic's validation errors as ``dotted.path: what to do`` lines.

Each line names the field (``mqtt.url``), what was wrong with the value, what is allowed (from
the field's declared bounds and choices), a close match for a misspelt key, and whether the value
came from an environment variable.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import annotated_types
from pydantic import BaseModel, ValidationError

__all__ = ["ConfigError", "describe_errors", "env_name", "environ_upper", "show_value"]

# DFFD_<SECTION>__<KEY> overrides section.key (pydantic-settings' env_prefix / nested delimiter).
ENV_PREFIX = "DFFD_"
ENV_NESTED_DELIMITER = "__"


class ConfigError(ValueError):
    """Invalid configuration; ``problems`` holds one ``dotted.path: what to do`` per field."""

    def __init__(self, problems: Sequence[str], source: str = "configuration") -> None:
        self.problems = list(problems)
        self.source = source
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"invalid {source}:\n{lines}")


def environ_upper() -> set[str]:
    """Names of the process environment's variables, upper-cased."""
    return {name.upper() for name in os.environ}


def env_name(section: str, key: str) -> str:
    """``DFFD_<SECTION>__<KEY>``: the variable that overrides ``section.key``."""
    return f"{ENV_PREFIX}{section}{ENV_NESTED_DELIMITER}{key}".upper()


def describe_errors(
    exc: ValidationError, data: Mapping[str, Any], root: type[BaseModel]
) -> Iterator[str]:
    """One ``dotted.path: what to do`` line per error of ``root`` validated from ``data``."""
    env = environ_upper()
    for error in exc.errors(include_url=False):
        loc = tuple(str(part) for part in error["loc"])
        ctx = error.get("ctx") or {}
        if error["type"] == "dffd_path":
            loc = tuple(str(ctx["path"]).split("."))
        elif error["type"] == "dffd_field":
            loc = (*loc, str(ctx["field"]))
        path = ".".join(loc) or "(top level)"
        line = f"{path}: {_explain(error, loc, root)}"
        if len(loc) >= 2 and env_name(loc[0], loc[1]) in env:
            line += f" (from environment variable {env_name(loc[0], loc[1])})"
        elif len(loc) == 1 and loc[0] not in data and error["type"] == "extra_forbidden":
            line += " (from the environment)"
        yield line


def _explain(error: Any, loc: tuple[str, ...], root: type[BaseModel]) -> str:
    kind: str = error["type"]
    value = error.get("input")
    ctx = error.get("ctx") or {}
    shown = show_value(value)
    if kind in {"dffd", "dffd_field", "dffd_path"}:
        return str(ctx["message"])
    if kind == "extra_forbidden":
        return _unknown_key(loc, root)
    if kind == "literal_error":
        return f"{shown} is not allowed; use {ctx['expected']}"
    if kind in {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}:
        return f"{shown} is out of range; {_range_text(loc, root) or error['msg'].lower()}"
    if kind in {"int_parsing", "int_type", "int_from_float"}:
        return f"{shown} is not an integer; {_range_text(loc, root) or 'give a whole number'}"
    if kind in {"float_parsing", "float_type", "finite_number"}:
        return f"{shown} is not a finite number; {_range_text(loc, root) or 'give a number'}"
    if kind in {"bool_parsing", "bool_type"}:
        return f"{shown} is not a boolean; use true or false"
    if kind in {"string_type", "path_type"}:
        return f'{shown} is not text; quote it, e.g. "..."'
    if kind in {"model_type", "model_attributes_type", "dict_type"}:
        return f"{shown} is not a table; write it as a [{loc[0]}] section with keys"
    if kind in {"tuple_type", "list_type", "too_short", "too_long"}:
        return f"{shown} has the wrong shape; {error['msg'].lower()}"
    return f"{error['msg']} (got {shown})"


def show_value(value: object) -> str:
    """``repr(value)``, shortened to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _unknown_key(loc: tuple[str, ...], root: type[BaseModel]) -> str:
    if len(loc) == 1:
        valid = list(root.model_fields)
        what, where = "unknown section", "valid sections"
    else:
        section_field = root.model_fields.get(loc[0])
        annotation = section_field.annotation if section_field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return "unknown key"
        valid = list(annotation.model_fields)
        what, where = "unknown key", f"valid keys in [{loc[0]}]"
    close = difflib.get_close_matches(loc[-1], valid, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"{what}{hint} ({where}: {', '.join(valid)})"


def _range_text(loc: tuple[str, ...], root: type[BaseModel]) -> str:
    """'allowed: 1 ≤ fps ≤ 240' from the field's declared bounds, or '' if it has none."""
    if len(loc) < 2:
        return ""
    section_field = root.model_fields.get(loc[0])
    annotation = section_field.annotation if section_field is not None else None
    if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
        return ""
    info = annotation.model_fields.get(loc[1])
    if info is None:
        return ""
    low = high = ""
    for meta in _bounds_metadata(info.metadata, info.annotation):
        if isinstance(meta, annotated_types.Ge):
            low = f"{meta.ge} ≤ "
        elif isinstance(meta, annotated_types.Gt):
            low = f"{meta.gt} < "
        elif isinstance(meta, annotated_types.Le):
            high = f" ≤ {meta.le}"
        elif isinstance(meta, annotated_types.Lt):
            high = f" < {meta.lt}"
    if not (low or high):
        return ""
    return f"allowed: {low}{loc[1]}{high}"


def _bounds_metadata(metadata: list[Any], annotation: Any) -> list[Any]:
    """Bounds declared on the field itself or inside an ``Annotated[...] | None`` annotation."""
    found = list(metadata)
    for arg in getattr(annotation, "__args__", ()):
        found.extend(getattr(arg, "__metadata__", ()))
    for meta in list(found):
        found.extend(getattr(meta, "metadata", ()))  # FieldInfo inside Annotated
    return found
