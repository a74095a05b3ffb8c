"""``export-urdf``: ``export --format urdf``, under the name earlier scripts use."""

from __future__ import annotations

import argparse

from hybrid_kinematics_ros.calibration.export import export
from hybrid_kinematics_ros.cli.export import add_export_args, write
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export-urdf", help="write the parametric stage's geometry as a URDF (export --format urdf)")
    add_export_args(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    return write(args, model, export(model, "urdf"), "urdf")
