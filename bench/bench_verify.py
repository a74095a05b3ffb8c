"""verify on the real UR10: a model trained on series A (four fifths, contiguous blocks), checked with A's
held-out fifth from the station it knows and with series D, measured months later from another tracker station
the model never saw (placed from every tenth of D's poses, the rest judged).

Usage: python -m bench.bench_verify [--steps S]
"""

from __future__ import annotations

import argparse

from bench.bench_export import trained_on_a
from bench.bench_real import load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration.verify import Tolerance, verify

TOLERANCE_MM = 0.1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=6000, help="optimiser steps per net")
    args = parser.parse_args()
    model, _, held_out = trained_on_a(args.steps)
    rows = []
    for label, pairs in (
        ("A, held-out fifth", held_out),
        ("D, another station", load_series("D", model.chain.joint_names)),
    ):
        result = verify(model, [pairs], Tolerance(TOLERANCE_MM))
        rows.append(
            [
                label,
                len(result.position_mm),
                f"{result.manifest()['position_mm_mean']:.4f}",
                f"{result.over_bound} ({100 * result.over_bound / len(result.position_mm):.1f} %)",
                f"{result.p_value:.2g}",
                "drifted" if result.drifted else "still calibrated",
                "PASS" if result.tolerance["passed"] else "FAIL",
                "; ".join(f"{d['what']}: {d['explained']:.0%}" for d in result.diagnosis) or "—",
            ]
        )
    head = [
        "check",
        "poses judged",
        "pos. mean (mm)",
        "beyond the 95 % bound",
        "p",
        "verdict",
        f"within {TOLERANCE_MM} mm (95 %)",
        "what explains the residual",
    ]
    write_section("verify", "verify on the real UR10 (bench_verify)", table(head, rows))


if __name__ == "__main__":
    main()
