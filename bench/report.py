"""Shared by the benchmark scripts: machine description and section-wise updates of BENCHMARKS.md."""

from __future__ import annotations

import os
import platform
import re
import shlex
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from hybrid_kinematics_ros.calibration.report import net_label

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"
HEADER = "# Benchmarks\n\nEvery section is written by the script it names; rerun it to refresh the numbers.\n"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{cpu}, {os.cpu_count()} cores, {mem_gb:.0f} GB, Python {platform.python_version()}, {platform.system()}"


def commit(script: str) -> str:
    """The commit the measured code is at, and whether the working tree changes it (bench/staleness.py)."""
    from bench.staleness import git, measured_paths

    try:
        head = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--", *measured_paths(script))
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return head + (" + uncommitted changes" if dirty else "")


def speed_check() -> str:
    """A yardstick of the machine's speed when a section is written: on this shared machine it varies up to
    threefold between runs, and every timing figure moves with it. One UR10 ``fk_single``, best of 5 × 2,000."""
    from hybrid_kinematics_ros.kinematics import fk
    from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

    chain = load_robot_config("ur10").chain
    q = chain.mid_limits()
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(2000):
            fk.fk_single(chain, q)
        best = min(best, (time.perf_counter() - start) / 2000)
    return f"one UR10 `fk_single` {1e6 * best:.1f} µs at the end of the run (best of 5 × 2,000)"


def write_section(key: str, title: str, body: str) -> None:
    """Replace (or append) the section ``key`` of BENCHMARKS.md."""
    module = "bench." + Path(sys.argv[0]).stem
    command = shlex.join(["python", "-m", module, *sys.argv[1:]])
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    section = (
        f"<!-- section:{key} -->\n## {title}\n\n"
        f"Command: `{command}`  \nMachine: {machine()}  \nSpeed check: {speed_check()}  \nRun: {stamp}  \n"
        f"Commit: {commit(Path(sys.argv[0]).stem)}\n\n"
        f"{body.strip()}\n<!-- end:{key} -->\n"
    )
    text = BENCHMARKS.read_text() if BENCHMARKS.exists() else HEADER
    pattern = re.compile(rf"<!-- section:{re.escape(key)} -->.*?<!-- end:{re.escape(key)} -->\n", re.S)
    text = pattern.sub(lambda _: section, text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    BENCHMARKS.write_text(text)
    print(section)


def table(headers: list[str], rows: list[list[object]]) -> str:
    def fmt(v: object) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def served(manifest: dict) -> str:
    """The nets' sizes as chosen on validation (or silenced), for a row's label."""
    nets = manifest.get("nets", {})

    def size(n: dict) -> str:
        return "off" if n.get("silenced") else net_label(n)

    return ", ".join(f"{k} {size(n)}" for k, n in nets.items())
