"""The real TIAGo against its floor, as a portfolio cell: a torso lift and a 7-joint arm, measured by motion
capture in four sessions of static postures over a week (``bench/real_tiago.py``), trained as ``bench_portfolio``
trains every cell (the capacity chosen, and the former constants beside it).

Two splits, both in time: the last session held out (trained on the three before it), and the other day held
out (trained on the three sessions of 2021-11-30, tested on 2021-11-26). The floor: pairs of postures
repeated in any two sessions (``calibration.floor``), so it holds what the robot does not repeat across days.

Usage: python -m bench.bench_tiago [--steps S]
"""

from __future__ import annotations

import argparse

from bench.bench_portfolio import FORMER, HEAD, evaluate_cell, row
from bench.bench_real import noise_floor
from bench.real_tiago import SESSIONS, load_session, tiago_config
from bench.report import table, write_section
from hybrid_kinematics_ros.io.pairs import Pairs


def tiago_cells():
    """(name, config, training sets, test sets, floor) of each split."""
    config = tiago_config()
    sessions = {name: load_session(name, config.chain.joint_names) for name in SESSIONS}
    pos, rot, _ = noise_floor(Pairs.concatenate(list(sessions.values())), config.chain)
    floor = {"position_mm_mean": pos, "position_mm_p95": float("nan"), "orientation_deg_mean": rot}
    first = Pairs.concatenate([sessions[n] for n in SESSIONS[:-1]])
    yield "real TIAGo, its last session held out", config, [first], [sessions[SESSIONS[-1]]], floor
    day = Pairs.concatenate([sessions[n] for n in SESSIONS[1:]])
    yield "real TIAGo, the other day held out", config, [day], [sessions[SESSIONS[0]]], floor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=3000, help="optimiser steps per net")
    args = parser.parse_args()
    rows = []
    for name, config, trains, tests, floor in tiago_cells():
        chosen = evaluate_cell(config, trains, tests, True, args.steps, None)
        former = evaluate_cell(config, trains, tests, True, args.steps, FORMER)
        rows.append(row(name, sum(len(p) for p in trains), floor, chosen, former))
        print(" | ".join(str(v) for v in rows[-1]), flush=True)
    body = (
        "Held-out errors at the hand body, in the motion capture's frame; columns as in the portfolio. The floor "
        "is the mean of |Δ residual| / √2 over postures repeated within 1 mrad in any two sessions. "
        f"Nets: `fast`, {args.steps:,} steps a net.\n\n" + table(HEAD, rows)
    )
    write_section("portfolio_tiago", "The real TIAGo against its floor (bench_tiago)", body)


if __name__ == "__main__":
    main()
