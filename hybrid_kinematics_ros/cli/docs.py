"""The command-line reference (docs/cli.md) rendered from the argparse definitions.

Run ``python -m hybrid_kinematics_ros.cli.docs > docs/cli.md`` after changing a subcommand's options.
The reference is built from the parser itself, not from ``--help`` text, so it cannot drift from what the
CLI accepts, and it does not depend on the terminal's width (argparse wraps help to $COLUMNS):
test/test_cli_docs.py regenerates it and fails when the committed file differs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator

REGENERATE = "python -m hybrid_kinematics_ros.cli.docs > docs/cli.md"


def render_cli_markdown(parser: argparse.ArgumentParser) -> str:
    """The whole reference: an index of the subcommands, then one section per subcommand (nested ones too)."""
    lines = [
        f"# `{parser.prog}` command-line reference",
        "",
        f"<!-- Generated from the argparse definitions by `{REGENERATE}`; do not edit by hand. -->",
        "",
    ]
    if parser.description:
        lines += [_text(parser.description), ""]
    commands = list(_subcommands(parser, ""))
    lines += [
        f"Usage: `{parser.prog} COMMAND [OPTIONS]`; `{parser.prog} COMMAND --help` prints a command's options.",
        "",
    ]
    lines += _options(parser)
    if commands:
        lines += ["| command | what it does |", "| --- | --- |"]
        lines += [f"| [`{name}`](#{_anchor(name)}) | {_cell(summary)} |" for name, summary, _ in commands]
        lines.append("")
    for name, summary, sub in commands:
        lines += [f"## `{name}`", ""]
        if summary:
            lines += [_text(summary), ""]
        if sub.description and sub.description != summary:
            lines += [_text(sub.description), ""]
        lines += [f"Usage: `{_usage(sub, f'{parser.prog} {name}')}`", ""]
        lines += _options(sub)
    return "\n".join(lines).rstrip("\n") + "\n"


def _subcommands(parser: argparse.ArgumentParser, prefix: str) -> Iterator[tuple[str, str, argparse.ArgumentParser]]:
    """(command words after the program's name, one-line help, parser) of every subcommand, depth first."""
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        helps = {choice.dest: choice.help or "" for choice in action._choices_actions}
        seen: set[int] = set()
        for name, sub in action.choices.items():
            if id(sub) in seen:  # an alias of a subcommand already listed
                continue
            seen.add(id(sub))
            command = f"{prefix} {name}".lstrip()
            yield command, helps.get(name, ""), sub
            yield from _subcommands(sub, command)


def _usage(parser: argparse.ArgumentParser, command: str) -> str:
    """A one-line usage: the command, its required options and positionals, then ``[OPTIONS]``."""
    parts = [command]
    grouped: set[int] = set()
    for group in parser._mutually_exclusive_groups:
        members = [a for a in group._group_actions if a.help is not argparse.SUPPRESS]
        grouped.update(id(a) for a in members)
        if group.required:
            parts.append("(" + " | ".join(_invocation(a, first_flag_only=True) for a in members) + ")")
    for action in parser._actions:
        if id(action) in grouped or action.help is argparse.SUPPRESS:
            continue
        if isinstance(action, argparse._SubParsersAction):
            parts.append("COMMAND")
        elif not action.option_strings or action.required:
            parts.append(_invocation(action, first_flag_only=True))
    if any(a.option_strings and not a.required and a.help is not argparse.SUPPRESS for a in parser._actions):
        parts.append("[OPTIONS]")
    return " ".join(parts)


def _options(parser: argparse.ArgumentParser) -> list[str]:
    """One table per argument group (argparse's "options" first), plus a note per mutually exclusive group."""
    lines: list[str] = []
    for group in parser._action_groups:
        actions = [
            a
            for a in group._group_actions
            if a.help is not argparse.SUPPRESS and not isinstance(a, argparse._HelpAction | argparse._SubParsersAction)
        ]
        if not actions:
            continue
        title = "arguments" if group.title == "positional arguments" else group.title or "options"
        title = title[:1].upper() + title[1:]  # not str.capitalize(): it would lower "URDF" in a title
        lines += [f"### {title}", ""]
        if group.description:
            lines += [_text(group.description), ""]
        lines += ["| option | default | description |", "| --- | --- | --- |"]
        for action in actions:
            invocation = _invocation(action).replace("|", "\\|")
            lines.append(f"| `{invocation}` | {_default(action)} | {_cell(_help(action, parser.prog))} |")
        lines.append("")
    for group in parser._mutually_exclusive_groups:
        flags = ", ".join(f"`{a.option_strings[0]}`" for a in group._group_actions if a.option_strings)
        lines += [f"{'Exactly' if group.required else 'At most'} one of: {flags}.", ""]
    return lines


def _invocation(action: argparse.Action, first_flag_only: bool = False) -> str:
    """``--flag VALUE`` as a user types it: every flag (or the first), then the value(s) with their metavar."""
    formatter = argparse.HelpFormatter(prog="")
    if not action.option_strings:
        return formatter._format_args(action, action.dest)
    flags = action.option_strings[:1] if first_flag_only else action.option_strings
    if action.nargs == 0:
        return ", ".join(flags)
    return ", ".join(flags) + " " + formatter._format_args(action, action.dest.upper())


def _default(action: argparse.Action) -> str:
    """The default as the table shows it: "required", on/off for switches, empty when there is none."""
    if action.required:
        return "required"
    default = action.default
    if default is None or default is argparse.SUPPRESS:
        return ""
    if isinstance(default, bool):
        return "on" if default else "off"
    if isinstance(default, list | tuple):
        return "`" + " ".join(map(str, default)) + "`"
    return f"`{default}`"


def _help(action: argparse.Action, prog: str) -> str:
    """The help text with argparse's %-substitutions applied (``%(default)s``, ``%%``) and the choices listed."""
    text = action.help or ""
    if text:
        params = {k: v for k, v in vars(action).items() if v is not argparse.SUPPRESS}
        params["prog"] = prog
        if params.get("choices") is not None:
            params["choices"] = ", ".join(map(str, params["choices"]))
        text = text % params
    if action.choices is not None and action.metavar is not None:
        text = (text + "; " if text else "") + "one of " + ", ".join(f"`{c}`" for c in action.choices)
    return text


def _text(text: str) -> str:
    """Free text as Markdown: one paragraph; angle brackets and asterisks shown, not taken for HTML or emphasis."""
    return " ".join(text.split()).replace("<", "&lt;").replace(">", "&gt;").replace("*", "\\*")


def _cell(text: str) -> str:
    """Free text inside a table cell, where a bare ``|`` would end the cell."""
    return _text(text).replace("|", "\\|")


def _anchor(heading: str) -> str:
    """The anchor GitHub gives a ``## `heading` `` line: lower case, spaces to dashes, other punctuation dropped."""
    return "".join(c for c in heading.lower().replace(" ", "-") if c.isalnum() or c in "-_")


def main() -> int:
    """Print the reference of ``hybrid-kinematics`` to stdout."""
    from hybrid_kinematics_ros.cli.main import build_parser

    sys.stdout.write(render_cli_markdown(build_parser()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
