"""Every benchmark, in sequence (about 3 hours on 2 cores); each writes its section of BENCHMARKS.md."""

from __future__ import annotations

import subprocess
import sys

STEPS = [
    ["bench.bench_fk"],
    ["bench.bench_cell"],
    ["bench.bench_hybrid", "inference"],
    ["bench.bench_ik"],
    ["bench.bench_ik_arms"],
    ["bench.bench_ik_approach"],
    ["bench.bench_nodes"],
    ["bench.bench_hybrid", "table1", "noise", "paper", "--minutes", "10"],
    ["bench.bench_hybrid", "curve", "--minutes", "8"],
    ["bench.bench_parametric", "referencing", "range", "table1", "--minutes", "10"],
]

if __name__ == "__main__":
    for step in STEPS:
        print("running", " ".join(step), flush=True)
        subprocess.run([sys.executable, "-m", *step], check=True)
