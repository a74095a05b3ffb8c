"""What each entry point imports: the numeric core never rclpy, and the nodes and CLI commands that load no
model never torch (a second of CPU at every start of the recorder, the simulated cell, ``simulate``, ...)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def imported(*modules: str, then: str = "") -> set[str]:
    """The top-level packages a fresh interpreter holds after importing ``modules`` and running ``then``."""
    listed = "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    code = f"import sys, {', '.join(modules)}\n{then}\n{listed}"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return set(out.split())


@pytest.mark.parametrize("node", ["recorder_node", "sim_cell_node"])
def test_the_nodes_without_nets_start_without_torch(node: str) -> None:
    packages = imported(f"hybrid_kinematics_ros.nodes.{node}")
    assert "rclpy" in packages and "torch" not in packages


def test_the_core_imports_without_rclpy() -> None:
    packages = imported(
        "hybrid_kinematics_ros.calibration.fit", "hybrid_kinematics_ros.ik.solver", "hybrid_kinematics_ros.cli.main"
    )
    assert "torch" in packages and "rclpy" not in packages


@pytest.mark.parametrize("command", ["simulate", "import", "align", "plan"])
def test_the_commands_that_load_no_model_start_without_torch(command: str) -> None:
    main = "hybrid_kinematics_ros.cli.main"
    assert "torch" not in imported(main, then=f"{main}.build_parser('{command}')")


def test_the_whole_cli_help_lists_every_command() -> None:
    from hybrid_kinematics_ros.cli.main import COMMANDS, build_parser

    whole = build_parser().format_help()
    assert all(name in whole for name in COMMANDS)
    assert "torch" in imported("hybrid_kinematics_ros.cli.main", then="hybrid_kinematics_ros.cli.main.build_parser()")
