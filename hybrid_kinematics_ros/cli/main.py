"""``hybrid-kinematics``: the offline workflow (plan, simulate, import, align, train, fk, ik, ...) as subcommands.

Every subsystem error ends the command with one line naming the bad file, field or value, and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from collections.abc import Sequence

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.chain import ImplausibleInertialWarning
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.simulation.errors import SimulationError

# each command's module, in the order the help lists them; a run imports only its own command's module, so the
# commands that load no model (simulate, import, align, plan) start without torch (about a second sooner)
COMMANDS = {
    "plan": "plan",
    "simulate": "simulate",
    "import": "import_",
    "align": "align",
    "train": "train",
    "evaluate": "evaluate",
    "report": "report",
    "verify": "verify",
    "update": "update",
    "compare": "compare",
    "fk": "fk",
    "ik": "ik",
    "compensate": "compensate",
    "export": "export",
    "export-urdf": "export_urdf",
}
USER_ERRORS: tuple[type[Exception], ...] = (
    CalibrationError,
    DataError,
    IKError,
    KinematicsError,
    ModelError,
    SimulationError,
)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The CLI's parser: every command's, or, with ``command``, that one's in full and the others' names."""
    parser = argparse.ArgumentParser(prog="hybrid-kinematics", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in COMMANDS.items():
        if command in (None, name):
            importlib.import_module(f"hybrid_kinematics_ros.cli.{module}").add_parser(sub)
            if name not in sub.choices:
                raise RuntimeError(f"cli/{module}.py registers no command '{name}'")
        else:
            sub.add_parser(name)  # this run parses another command
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(command if command in COMMANDS else None).parse_args(argv)
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
