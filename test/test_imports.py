"""What each entry point imports: the numeric core never rclpy, and the nodes that serve no nets never torch
(a second of CPU at every start of the recorder and the simulated cell)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def imported(*modules: str) -> set[str]:
    """The top-level packages a fresh interpreter holds after importing ``modules``."""
    code = f"import sys, {', '.join(modules)}; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
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
