"""Which sections of BENCHMARKS.md still describe the code: each section's commit against the commits that
have touched the code it measures since.

A section ran at the commit its ``Commit:`` line names. A section run from a working tree with uncommitted
changes, or one written before sections carried a commit, ran at the commit that brought its ``Run:`` line into
BENCHMARKS.md (git blame): its numbers were committed together with the code they measured.

The code a section measures: its script and every file of the package and of bench/ that it imports, directly or
through the files it imports (the closure over their imports, lazy ones included), and ``config/`` (the robots'
URDFs and parameters), but not the files that only write the sections (``WRITERS``). A section is stale when a
commit after the one it ran at touched any of it.

``python -m bench.staleness`` lists the sections and marks the stale ones in BENCHMARKS.md; ``--check`` only
lists them and exits 1 if any is stale.
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "hybrid_kinematics_ros"
ALWAYS = ("config",)
# how sections are written, not what they measure: a change here leaves every figure as it was
WRITERS = ("bench/__init__.py", "bench/report.py", "bench/staleness.py")
SECTION = re.compile(r"<!-- section:(?P<key>[\w-]+) -->\n(?P<body>.*?)<!-- end:(?P=key) -->\n", re.S)
STALE_LINE = re.compile(r"^\*\*Stale:\*\*.*\n\n?", re.M)


@dataclass(frozen=True)
class Section:
    key: str
    script: str | None  # "bench_fk", from the Command line
    ran_at: str | None  # full commit hash
    stale_since: str | None  # the newest commit after ran_at that touched the measured code
    measured: tuple[str, ...]


def git(*args: str, root: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout.strip()


def _module_file(module: str, root: Path) -> Path | None:
    path = root.joinpath(*module.split("."))
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(path: Path, root: Path) -> set[Path]:
    """The files of ``PACKAGE`` and ``bench`` that ``path`` imports, at any depth of its code (a lazy import
    inside a function runs when that function does), and the packages' ``__init__.py`` on the way."""
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the importing file's package upwards
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base]) if base else ".".join(parts)
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] not in (PACKAGE, "bench"):
                continue
            for depth in range(1, len(parts) + 1):  # a package's __init__ runs on the way to its modules
                file = _module_file(".".join(parts[:depth]), root)
                if file is not None:
                    found.add(file)
    return found


def measured_paths(script: str, root: Path = ROOT) -> tuple[str, ...]:
    """The files (relative to ``root``) whose change can change what ``bench/<script>.py`` measures: the
    closure of its imports within the package and bench/, file by file."""
    todo = [root / "bench" / f"{script}.py"]
    seen: set[Path] = set()
    while todo:
        file = todo.pop()
        if file in seen or not file.is_file():
            continue
        seen.add(file)
        todo.extend(_imports(file, root) - seen)
    paths = {str(file.relative_to(root)) for file in seen} - set(WRITERS)
    if any(path.startswith(f"{PACKAGE}/nodes/") for path in paths):
        paths.add("hybrid_kinematics_interfaces")
    return tuple(sorted(paths)) + ALWAYS


def _ran_at(key: str, body: str, benchmarks: Path, root: Path) -> str | None:
    commit = re.search(r"^Commit: ([0-9a-f]{7,40})(?P<dirty> \+ uncommitted changes)?", body, re.M)
    if commit and not commit.group("dirty"):
        return git("rev-parse", commit.group(1), root=root)
    text = benchmarks.read_text()
    start = text.index(f"<!-- section:{key} -->")
    run = re.compile(r"^Run: .*$", re.M).search(text, start)
    if run is None:
        return None
    line = text.count("\n", 0, run.start()) + 1
    try:
        blame = git("blame", "--porcelain", "-L", f"{line},{line}", "--", str(benchmarks.relative_to(root)), root=root)
    except subprocess.CalledProcessError:
        return None
    sha = blame.split()[0]
    return None if set(sha) == {"0"} else sha  # all zeros: not committed yet


def sections(benchmarks: Path | None = None, root: Path = ROOT) -> list[Section]:
    benchmarks = benchmarks or root / "BENCHMARKS.md"
    out = []
    for match in SECTION.finditer(benchmarks.read_text()):
        key, body = match.group("key"), match.group("body")
        command = re.search(r"^Command: `python -m bench\.(\w+)", body, re.M)
        script = command.group(1) if command else None
        ran_at = _ran_at(key, body, benchmarks, root)
        measured = measured_paths(script, root) if script else ()
        stale = None
        if ran_at and measured:
            stale = git("log", "-1", "--format=%H", f"{ran_at}..HEAD", "--", *measured, root=root) or None
        elif ran_at is None or not measured:
            stale = "unknown"
        out.append(Section(key, script, ran_at, stale, measured))
    return out


def describe(section: Section, root: Path = ROOT) -> str:
    if section.stale_since is None:
        return f"current: ran at {section.ran_at[:10]}; nothing it measures has changed since"
    if section.stale_since == "unknown":
        return "unknown: no commit or no script recorded for it"
    return f"stale: {_change(section, root)}"


def _change(section: Section, root: Path) -> str:
    sha, day, subject = git("log", "-1", "--format=%h%x00%cs%x00%s", section.stale_since, root=root).split("\0")
    subject = subject if len(subject) <= 72 else subject[:71].rsplit(" ", 1)[0] + " …"
    return f"ran at {section.ran_at[:10]}; the code it measures changed after, last in {sha} ({day}, “{subject}”)"


def mark(benchmarks: Path | None = None, root: Path = ROOT) -> list[Section]:
    """Write a ``**Stale:**`` line into every stale section (and remove it from current ones)."""
    benchmarks = benchmarks or root / "BENCHMARKS.md"
    found = {s.key: s for s in sections(benchmarks, root)}

    def update(match: re.Match) -> str:
        key, body = match.group("key"), STALE_LINE.sub("", match.group("body"))
        section = found[key]
        if section.stale_since is not None:
            what = _change(section, root) if section.stale_since != "unknown" else "no commit recorded for it"
            note = f"**Stale:** {what}. Rerun its command to refresh it.\n\n"
            title_end = body.index("\n") + 1  # after the "## title" line and its blank line
            body = body[:title_end] + "\n" + note + body[title_end:].lstrip("\n")
        return f"<!-- section:{key} -->\n{body}<!-- end:{key} -->\n"

    benchmarks.write_text(SECTION.sub(update, benchmarks.read_text()))
    return list(found.values())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="list only; exit 1 if a section is stale")
    args = parser.parse_args(argv)
    found = sections() if args.check else mark()
    for section in found:
        print(f"{section.key:24s} {describe(section)}")
    return 1 if args.check and any(s.stale_since for s in found) else 0


if __name__ == "__main__":
    sys.exit(main())
