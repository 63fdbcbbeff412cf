"""The command line's documentation: ``--help`` states every default, and README.md's command table and Python
snippet match the parser and the API (no JAX: the parser is built, never run)."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from test_stats import planted

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


REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"


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


def readme_python() -> str:
    """The ```python block of README.md."""
    return re.search(r"```python\n(.*?)```", README.read_text(), re.S).group(1)


def readme_cli_lines() -> list[list[str]]:
    """The indented ``.venv/bin/wbc-jax`` command lines of README.md's first section, as argument lists."""
    return [line.split()[1:] for line in README.read_text().splitlines()
            if line.startswith("    .venv/bin/wbc-jax ")]


def test_readme_snippet_runs_after_the_cli_lines(tmp_path):
    """The README's CLI lines' outputs exist (the campaign's results table stands in for its run: the snippet
    only reads it; the report line runs), then the Python snippet runs as written, in a fresh interpreter."""
    lines = readme_cli_lines()
    assert [line[0] for line in lines] == ["campaign", "report"]
    out = Path(tmp_path, lines[0][lines[0].index("--out") + 1])
    out.mkdir(parents=True)
    df = planted(seed=5)
    df["S"] = 0.5 + 0.01 * df["R"]
    df.to_csv(out / "results.csv", index=False)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    for code in (f"from wbc_jax.cli import main; raise SystemExit(main({lines[1]!r}))", readme_python()):
        r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "out" / "report" / "anova.json").exists()


def test_python_api_speaks_python(tmp_path):
    """An output folder the API refuses names the keyword argument, not the CLI flag."""
    import wbc_jax
    from wbc_jax.api import python_wording
    from wbc_jax.errors import OutputError

    planted(seed=5).to_csv(tmp_path / "results.csv", index=False)
    wbc_jax.report(tmp_path / "results.csv", tmp_path / "report", figures=False)
    with pytest.raises(OutputError, match="force=True") as refused:
        wbc_jax.report(tmp_path / "results.csv", tmp_path / "report", figures=False)
    assert "--" not in str(refused.value)
    assert python_wording("--out d: continue with --resume, or --force; --allow-large") == (
        "out=d: continue with resume=True, or force=True; allow_large=True")
    assert python_wording("write it with wbc-jax report r.csv --out x; or --force") == (
        "write it with wbc-jax report r.csv --out x; or force=True")
