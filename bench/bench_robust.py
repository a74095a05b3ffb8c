"""Outliers judged on what the stage leaves: cells whose URDF model is centimetres off, with and without broken
beams, and real cells, each trained as ``train`` trains (capacity chosen; nets of a few steps, since only the
stage is read here).

Per cell: what the URDF model misses after the rigid referencing (rms) and how many pairs that referencing counts
as outliers; the pairs the stage leaves beyond five robust standard deviations and that limit; where broken
beams were added, how many of them the stage found and how many of its outliers they are; the stage's held-out
mean position error with the outliers kept (down-weighted) and with them dropped and the stage fitted again,
side by side; and the cell's floor.

Usage: python -m bench.bench_robust
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from bench.bench_portfolio import evaluate_cell, real_cells
from bench.bench_tiago import tiago_cells
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration.fit import identify_stations, reference_all
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.simulation.portfolio import CENTIMETRES_OFF, REALISTIC, CellSpec, build_cell

BROKEN_EVERY = 20  # one training pair in this many moved by a broken beam
BROKEN_MM = 3.0  # per axis, standard deviation


def broken(pairs: Pairs) -> tuple[Pairs, np.ndarray]:
    bad = np.arange(0, len(pairs), BROKEN_EVERY)
    T = pairs.T.copy()
    T[bad, :3, 3] += np.random.default_rng(5).normal(0.0, 1e-3 * BROKEN_MM, (len(bad), 3))
    return replace(pairs, T=T), bad


def position_only(pairs: Pairs) -> Pairs:
    T = pairs.T.copy()
    T[:, :3, :3] = np.eye(3)
    return replace(pairs, T=T, position_only=True)


def cells():
    """(name, config, training pairs, test pairs, floor (mm) or None, the broken pairs or None)."""
    for plain in (False, True):
        spec = CellSpec("off", poses=300, truth=CENTIMETRES_OFF, plain_reflector=plain, **REALISTIC)
        cell = build_cell(spec)
        what = "plain reflector" if plain else "6-D"
        floor = cell.floor["position_mm_mean"]
        yield f"UR10, URDF centimetres off, {what}, 300 poses", cell.config, cell.train, cell.test, floor, None
        pairs, bad = broken(cell.train)
        name = f"the same, 1 pair in {BROKEN_EVERY} broken by {BROKEN_MM:g} mm"
        yield name, cell.config, pairs, cell.test, floor, bad
    for name, config, trains, tests, floor in real_cells():
        if name == "real UR10 A, 1,000 poses":
            yield name, config, trains[0], tests[0], floor["position_mm_mean"], None
    for name, config, trains, tests, floor in tiago_cells():
        if "last session" in name:
            yield name, config, trains[0], tests[0], floor["position_mm_mean"], None
            tr, te = position_only(trains[0]), position_only(tests[0])
            yield name + ", position only", config, tr, te, floor["position_mm_mean"], None


def row(name, config, train, test, floor, bad) -> list:
    rigid = next(iter(reference_all(config.chain, [train]).values()))
    kept, _, _ = evaluate_cell(config, [train], [test], True, 30, None, drop_outliers=False)
    errors, manifest, _ = evaluate_cell(config, [train], [test], True, 30, None)
    outliers = manifest["parametric"].get("dropped", manifest["parametric"]["outliers"])  # the first fit's
    found = "—"
    if bad is not None:  # which pairs the stage names: identified again on every training pair
        _, result = identify_stations(config.chain, [train], reference_all(config.chain, [train]))
        named = result.outliers
        found = f"{np.isin(bad, named).sum()} of {len(bad)} / {np.isin(named, bad).sum()} of {len(named)}"
    stage = errors["parametric stage"]["position_mm_mean"]
    return [
        name,
        len(train),
        f"{rigid.rms_position_mm:.3f}",
        f"{rigid.outliers}",
        f"{outliers['pairs']} (beyond {outliers['beyond_mm']:.4f})",
        found,
        f"{kept['parametric stage']['position_mm_mean']:.4f}",
        f"{stage:.4f}",
        "—" if floor is None else f"{floor:.4f}",
    ]


HEAD = [
    "cell",
    "training pairs",
    "URDF model after the rigid referencing: rms (mm)",
    "its outliers",
    "the stage's outliers (mm)",
    "broken beams found / of the stage's outliers",
    "stage held-out pos. mean, outliers kept (mm)",
    "… dropped (mm)",
    "floor (mm)",
]


def main() -> None:
    rows = []
    for cell in cells():
        rows.append(row(*cell))
        print(" | ".join(str(v) for v in rows[-1]), flush=True)
    body = (
        "The robust loss's scale comes from the data: five robust standard deviations (1.4826 × the median "
        "absolute residual) of what each fit leaves, the stage fitted twice (at the scale of its start, then at "
        "that of the first fit's end); an outlier is a pair the stage leaves beyond five of them. Each cell is "
        "trained twice side by side: with the outliers kept, down-weighted, and with them dropped and the "
        "referencing, the stage and the nets fitted again without them (`train`'s default). The rigid "
        "referencing's outliers are judged the same way against its own residuals. Broken beams: "
        f"one training pair in {BROKEN_EVERY} moved by {BROKEN_MM:g} mm (standard deviation per axis); the stage is "
        "identified again on every training pair to name them. Stage errors: held out as in the portfolio (the "
        "virtual cells' test walk; UR10 A's held-out fifth in blocks; the TIAGo's last session). Floors as in the "
        "portfolio and bench_tiago.\n\n" + table(HEAD, rows)
    )
    write_section("robust", "Outliers judged on what the stage leaves", body)


if __name__ == "__main__":
    main()
