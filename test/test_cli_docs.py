"""docs/cli.md is what ``hybrid_kinematics_ros.cli.docs`` renders from today's argparse definitions.

The reference is generated, so an option added, renamed or re-documented in a subcommand must come with a
regenerated file; this test is what makes a stale reference fail CI instead of misleading a reader.
"""

from __future__ import annotations

import argparse

from hybrid_kinematics_ros.cli.docs import REGENERATE, render_cli_markdown
from hybrid_kinematics_ros.cli.main import build_parser
from test.conftest import ROOT

CLI_MD = ROOT / "docs" / "cli.md"


def test_cli_md_is_up_to_date() -> None:
    expected = render_cli_markdown(build_parser())
    committed = CLI_MD.read_text() if CLI_MD.is_file() else ""
    assert committed == expected, f"docs/cli.md is stale: run {REGENERATE}"


def test_every_subcommand_and_option_is_documented() -> None:
    """The renderer leaves nothing out: each subcommand has a section and each of its flags appears in it."""
    parser = build_parser()
    text = render_cli_markdown(parser)
    (subparsers,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    sections = text.split("\n## ")
    for name, sub in subparsers.choices.items():
        section = next((s for s in sections if s.startswith(f"`{name}`\n")), None)
        assert section is not None, f"no section for {name}"
        for action in sub._actions:
            if action.help is argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
                continue
            for flag in action.option_strings:
                assert f"`{flag}" in section or f", {flag}" in section, f"{name}: {flag} missing"


def test_rendering_does_not_depend_on_the_terminal(monkeypatch) -> None:
    """argparse wraps its own help to $COLUMNS; the reference must be the same on every terminal and in CI."""
    monkeypatch.setenv("COLUMNS", "40")
    narrow = render_cli_markdown(build_parser())
    monkeypatch.setenv("COLUMNS", "250")
    assert render_cli_markdown(build_parser()) == narrow
