"""README.md cannot drift from the code: its MQTT topic table, its MQTT command table and its
``dffd`` command table are checked against the tables the program runs on."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import get_args

import jsonschema

from dffd.cli import SUBCOMMANDS, build_parser
from dffd.exitcodes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from dffd.mqtt import models, schemas
from dffd.mqtt.topics import TOPIC_POLICY

README = (Path(__file__).resolve().parent.parent / "README.md").read_text(encoding="utf-8")
TICKED = re.compile(r"`([^`]+)`")


def section(title: str) -> str:
    """The README text from the heading ``title`` to the next heading of the same level."""
    match = re.search(rf"^(#+) {re.escape(title)}\n(.*?)(?=^\1 |\Z)", README, re.M | re.S)
    assert match is not None, f"README has no section {title!r}"
    return match.group(2)


def table_rows(text: str, first_header: str) -> list[list[str]]:
    """The body rows (cells) of the markdown table whose first header cell is ``first_header``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split(" | ")])
    return rows


def test_every_topic_is_documented_with_its_qos_and_retain_flag() -> None:
    rows = table_rows(section("MQTT interface"), "topic")
    documented = {}
    for cells in rows:
        leaf = TICKED.search(cells[0])
        assert leaf is not None, cells
        documented[leaf.group(1).removeprefix("…/")] = (int(cells[1]), cells[2] == "yes")
    expected = {leaf: (qos, retain) for leaf, qos, retain in TOPIC_POLICY.values()}
    assert documented == expected


def test_every_topic_has_an_example_payload() -> None:
    text = section("Example payloads")
    for leaf, _qos, _retain in TOPIC_POLICY.values():
        assert f"dffd/sim/{leaf} " in text, f"no example payload of …/{leaf}"


def test_the_example_payloads_are_complete_and_valid() -> None:
    # Each example validates against the shipped schema of its topic and carries every field of
    # that schema (so a field added to a payload must be shown here too); commands are checked
    # by the command parser.
    kinds = {leaf: kind for kind, (leaf, _qos, _retain) in TOPIC_POLICY.items()}
    seen = set()
    for line in section("Example payloads").splitlines():
        if not line.startswith("dffd/sim/"):
            continue
        topic, payload = line.split(" ", 1)
        leaf = topic.removeprefix("dffd/sim/")
        doc = json.loads(payload)
        seen.add(leaf)
        if kinds[leaf] == "cmd":
            if doc["cmd"] in models.COMMAND_NAMES:
                models.parse_command(payload)
            continue
        schema = schemas.load(kinds[leaf])
        jsonschema.validate(doc, schema)
        assert set(schema["properties"]) <= set(doc), (leaf, set(schema["properties"]) - set(doc))
    assert seen == set(kinds)


def test_every_command_is_documented_with_its_arguments() -> None:
    rows = table_rows(section("MQTT interface"), "command")
    documented = {}
    for cells in rows:
        name = TICKED.search(cells[0])
        assert name is not None, cells
        documented[name.group(1)] = set(re.findall(r"`([a-z_]+)`:", cells[1]))
    classes = get_args(get_args(models.Command)[0])
    expected = {
        cls.model_fields["cmd"].annotation.__args__[0]: set(cls.model_fields) - {"cmd", "id"}
        for cls in classes
    }
    assert set(expected) == set(models.COMMAND_NAMES)
    assert documented == expected


def test_every_dffd_subcommand_is_documented_with_every_option() -> None:
    rows = table_rows(section("Running it"), "command")
    documented: dict[str, set[str]] = {}
    for cells in rows:
        usage = TICKED.search(cells[0])
        assert usage is not None, cells
        words = usage.group(1).split()
        if words[0] == "dffd":
            options = set(re.findall(r"--[a-z][a-z0-9-]*", usage.group(1)))
            documented[words[1]] = documented.get(words[1], set()) | options  # rows add up
    assert set(documented) == set(SUBCOMMANDS)
    for name in SUBCOMMANDS:
        parser = build_parser(name)
        sub = next(
            action for action in parser._actions if isinstance(action, argparse._SubParsersAction)
        ).choices[name]
        options = {
            option
            for action in sub._actions
            if action.help != argparse.SUPPRESS
            for option in action.option_strings
            if option.startswith("--") and option != "--help"
        }
        assert documented[name] == options, name


def test_the_exit_codes_are_the_programs() -> None:
    text = section("Exit codes")
    codes = {int(cells[0].strip("`")) for cells in table_rows(text, "code")}
    assert codes == {EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED}
