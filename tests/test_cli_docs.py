"""The command line's documentation: ``--help`` states every default, and README.md's command table and Python
snippet match the parser and the API (no JAX: the parser is built, never run)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from wbc_jax.cli.parser import build_parser


def subparsers() -> dict[str, argparse.ArgumentParser]:
    """The ``wbc-jax`` subcommands' parsers by name."""
    action = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_help_states_every_default():
    top = build_parser()
    assert "console script" not in top.description and "campaign" in top.description
    for name, parser in subparsers().items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or isinstance(action, (argparse._HelpAction, argparse._StoreTrueAction)):
                continue
            text = formatter._get_help_string(action)
            assert action.required or "default" in text, f"wbc-jax {name} {action.option_strings[0]}: {text!r}"
        parser.format_help()  # every help string formats


README = Path(__file__).resolve().parents[1] / "README.md"


def command_table() -> dict[str, str]:
    """README.md's command table: the command cell (markdown escapes removed) by subcommand name."""
    text = README.read_text()
    section = text[text.index("## Command line"):]
    rows = {}
    for line in section.splitlines()[1:]:
        if line.startswith("## "):
            break
        cells = re.split(r"(?<!\\)\|", line)
        if len(cells) > 2 and cells[1].strip().startswith("`wbc-jax "):
            command = cells[1].strip().strip("`").replace("\\|", "|")
            rows[command.split()[1]] = command
    return rows


def test_command_table_matches_parser():
    table, parsers = command_table(), subparsers()
    assert set(table) == set(parsers), "README.md's command table and the parser list different subcommands"
    for name, command in table.items():
        parser = parsers[name]
        options = {s: a for a in parser._actions for s in a.option_strings}
        in_required_group = {a for g in parser._mutually_exclusive_groups if g.required for a in g._group_actions}
        mandatory = set(re.findall(r"--[a-z][a-z0-9-]*", re.sub(r"\[[^\]]*\]", "", command)))
        for flag in re.findall(r"--[a-z][a-z0-9-]*", command):
            assert flag in options, f"README.md: wbc-jax {name} {flag}: no such flag"
            action = options[flag]
            required = action.required or action in in_required_group
            assert required == (flag in mandatory), (
                f"README.md: wbc-jax {name} {flag} is {'' if required else 'not '}required; the table says otherwise")
        if "--force" in options:
            assert "--force" in command, f"README.md: wbc-jax {name}: --force missing"
