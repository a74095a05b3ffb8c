"""``compare``: two calibrations of one robot side by side: moved parameters, tip difference, a shared check."""

from __future__ import annotations

import argparse
import html
import json
from pathlib import Path

import numpy as np

from hybrid_kinematics_ros.calibration.compare import Comparison, compare
from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="two models of one robot: parameters moved beyond 3 σ, tip difference, a check")
    p.add_argument("model_a", type=Path, help="model directory A (the reference, e.g. the older calibration)")
    p.add_argument("model_b", type=Path, help="model directory B")
    p.add_argument("--bag", nargs="+", help="a check's pairs bag(s) or raw recordings to verify both models on")
    p.add_argument("--json", type=Path, help="write the comparison as JSON here")
    p.add_argument("--out", type=Path, help="write an HTML page with a plot per joint into this folder")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    a, b = HybridModel.load(args.model_a), HybridModel.load(args.model_b)
    check = load_stations(args.bag, a.chain) if args.bag else ()
    result = compare(a, b, check)
    lines = result.lines()
    print("\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps(result.manifest(), indent=2))
    if args.out:
        _page(result, lines, a, args)
    return 0


def _page(result: Comparison, lines: list[str], a: HybridModel, args: argparse.Namespace) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    plot = _joint_plot(result, a.chain.joint_names, args.out / "tip_difference.png")
    head = ["parameter", "A", "σ A", "B", "σ B", "unit", "change (σ)"]
    rows = "".join(
        f"<tr{' class=flagged' if p['flagged'] else ''}>"
        + "".join(
            f"<td>{html.escape(v if isinstance(v, str) else f'{v:.4g}' if v is not None else '')}</td>"
            for v in (p["name"], p["a"], p["sigma_a"], p["b"], p["sigma_b"], p["unit"], p["sigmas"])
        )
        + "</tr>"
        for p in result.parameters
    )
    items = "".join(f"<li>{html.escape(line)}</li>" for line in lines)
    title = f"{html.escape(str(args.model_a))} against {html.escape(str(args.model_b))}"
    (args.out / "index.html").write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>compare {title}</title>"
        "<style>.flagged{background:#fdd} td,th{padding:2px 8px}</style></head>"
        f"<body><h1>{title}</h1><ul>{items}</ul><h2>Tip difference (B − A) per joint</h2>"
        f"<img src='{plot.name}' alt='tip difference per joint'><h2>Parameters</h2><table><tr>"
        + "".join(f"<th>{h}</th>" for h in head)
        + f"</tr>{rows}</table></body></html>"
    )


def _joint_plot(result: Comparison, names: tuple[str, ...], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = 3
    fig, axes = plt.subplots(-(-len(names) // columns), columns, figsize=(12, 3.2 * -(-len(names) // columns)))
    for ax, j, name in zip(np.ravel(axes), range(len(names)), names, strict=False):
        ax.plot(np.degrees(result.q[:, j]), result.position_mm, ".", ms=2, alpha=0.4)
        ax.set_xlabel(f"{name} (deg)")
        ax.set_ylabel("position difference (mm)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
