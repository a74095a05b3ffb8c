"""``hybrid-kinematics``: the offline workflow (plan, simulate, import, align, train, fk, ik, ...) as subcommands.

Every subsystem error ends the command with one line naming the bad file, field or value, and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.cli import (
    align,
    compensate,
    evaluate,
    export_urdf,
    fk,
    ik,
    import_,
    plan,
    report,
    simulate,
    train,
)
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.chain import ImplausibleInertialWarning
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.simulation.errors import SimulationError

COMMANDS = [plan, simulate, import_, align, train, evaluate, report, fk, ik, compensate, export_urdf]
USER_ERRORS: tuple[type[Exception], ...] = (
    CalibrationError,
    DataError,
    IKError,
    KinematicsError,
    ModelError,
    SimulationError,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hybrid-kinematics", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    default_show = warnings.showwarning

    def show(message, category, *rest, **kwargs) -> None:
        """Our own warnings as one plain line each, like the errors; others as Python shows them."""
        if issubclass(category, ImplausibleInertialWarning):
            print(f"hybrid-kinematics {args.command}: warning: {message}", file=sys.stderr)
        else:
            default_show(message, category, *rest, **kwargs)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            return int(args.run(args) or 0)
    except USER_ERRORS as exc:
        print(f"hybrid-kinematics {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hybrid-kinematics {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
