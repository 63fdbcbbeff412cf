"""The command line's documentation: ``--help`` states every default, and README.md's command table and Python
snippet match the parser and the API (no JAX: the parser is built, never run)."""

from __future__ import annotations

import argparse

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
