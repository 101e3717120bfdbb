"""JSON Schemas of the MQTT payloads, generated from the pydantic models and shipped.

``python -m dffd.mqtt.schemas --out dffd/schemas`` (re)writes ``<topic>.schema.json`` per topic;
a test checks that the committed files equal what this module generates. Published payloads use
the serialization schema (every key present); commands use the validation schema (optional keys
may be left out).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from dffd.mqtt.models import (
    COMMAND_ADAPTER,
    CommandReply,
    Estimate,
    Measurement,
    Status,
    Truth,
)
from dffd.mqtt.topics import TOPIC_POLICY, TopicKind

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_PACKAGE = "dffd.schemas"

_PUBLISHED: dict[TopicKind, type[BaseModel]] = {
    "estimate": Estimate,
    "measurement": Measurement,
    "status": Status,
    "cmd_reply": CommandReply,
    "sim_truth": Truth,
}


def schema_filename(kind: TopicKind) -> str:
    """``cmd/reply`` -> ``cmd-reply.schema.json``."""
    return TOPIC_POLICY[kind][0].replace("/", "-") + ".schema.json"


def generate() -> dict[str, dict[str, Any]]:
    """Every payload's JSON Schema, keyed by file name."""
    out: dict[str, dict[str, Any]] = {}
    for kind, model in _PUBLISHED.items():
        schema = model.model_json_schema(by_alias=True, mode="serialization")
        out[schema_filename(kind)] = _decorate(schema, kind)
    command = COMMAND_ADAPTER.json_schema(by_alias=True, mode="validation")
    command["title"] = "Command"
    out[schema_filename("cmd")] = _decorate(command, "cmd")
    return dict(sorted(out.items()))


def render(schema: dict[str, Any]) -> str:
    """Stable text form of a schema (what is written and compared)."""
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def write(out_dir: Path) -> list[Path]:
    """Write every schema file into ``out_dir``; return the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in generate().items():
        path = out_dir / name
        path.write_text(render(schema), encoding="utf-8")
        written.append(path)
    return written


def load(kind: TopicKind) -> dict[str, Any]:
    """The shipped schema of ``kind`` (from package data)."""
    text = resources.files(SCHEMA_PACKAGE).joinpath(schema_filename(kind)).read_text("utf-8")
    loaded: dict[str, Any] = json.loads(text)
    return loaded


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m dffd.mqtt.schemas --out DIR``."""
    parser = argparse.ArgumentParser(prog="python -m dffd.mqtt.schemas", description=__doc__)
    parser.add_argument("--out", type=Path, required=True, help="directory, e.g. dffd/schemas")
    args = parser.parse_args(argv)
    for path in write(args.out):
        print(path)
    return 0


def _decorate(schema: dict[str, Any], kind: TopicKind) -> dict[str, Any]:
    leaf, qos, retain = TOPIC_POLICY[kind]
    return {
        "$schema": SCHEMA_DIALECT,
        "$id": f"https://dffd.invalid/schemas/{schema_filename(kind)}",
        "description": f"Payload of <prefix>/<camera>/{leaf} (QoS {qos}"
        f"{', retained' if retain else ''}). {schema.get('description', '')}".strip(),
        **{k: v for k, v in schema.items() if k != "description"},
    }


if __name__ == "__main__":
    sys.exit(main())
