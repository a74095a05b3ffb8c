"""Keeps BENCHMARKS.md true: marks every section whose measured code changed after it ran (bench/staleness.py)
and, with ``--rerun``, runs the commands of the stale sections again (hours on 2 cores), each once, so that
they write their sections anew; with ``--all``, every benchmark in ``STEPS``."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys

from bench.staleness import ROOT, describe, mark

STEPS = [
    ["bench.bench_fk"],
    ["bench.bench_cell"],
    ["bench.bench_hybrid", "inference"],
    ["bench.bench_ik"],
    ["bench.bench_ik_arms"],
    ["bench.bench_ik_approach"],
    ["bench.bench_nodes"],
    ["bench.bench_clock"],
    ["bench.bench_hybrid", "table1", "noise", "paper", "--minutes", "10"],
    ["bench.bench_hybrid", "curve", "--minutes", "8"],
    ["bench.bench_parametric", "referencing", "range", "table1", "--minutes", "10"],
    ["bench.bench_one_orientation"],
    ["bench.bench_export"],
    ["bench.bench_lifecycle"],
]


def stale_commands() -> list[list[str]]:
    """The commands of the stale sections, each once, in the order of BENCHMARKS.md."""
    text = (ROOT / "BENCHMARKS.md").read_text()
    commands: list[list[str]] = []
    for section in mark():
        if section.stale_since is None:
            continue
        start = text.index(f"<!-- section:{section.key} -->")
        line = text[start:].split("Command: `", 1)[1].split("`", 1)[0]
        argv = shlex.split(line)[2:] if line.startswith("python -m ") else []
        if argv and argv not in commands:
            commands.append(argv)
    return commands


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rerun", action="store_true", help="rerun the stale sections' commands")
    parser.add_argument("--all", action="store_true", help="rerun every benchmark in STEPS")
    args = parser.parse_args(argv)
    commands = STEPS if args.all else stale_commands() if args.rerun else []
    failed = []
    for step in commands:
        print("running", shlex.join(step), flush=True)
        if subprocess.run([sys.executable, "-m", *step], cwd=ROOT, check=False).returncode:
            failed.append(shlex.join(step))
    found = mark()
    for section in found:
        print(f"{section.key:24s} {describe(section)}")
    stale = sum(1 for s in found if s.stale_since)
    print(f"{stale} of {len(found)} sections stale" + (f"; failed: {failed}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
