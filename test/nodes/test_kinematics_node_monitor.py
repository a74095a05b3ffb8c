"""The kinematics node watching the tracker while it serves: the simulated cell streams joint states and the
tracker's poses from a station the model never saw; the node places the station, judges the still poses, and
reports on /diagnostics, OK while the robot is unchanged and WARN once a joint slips."""

from __future__ import annotations

import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from test.nodes.rosutil import Client, start, stop

pytestmark = pytest.mark.ros
SLIP_AFTER_S = 35.0  # the sim's clock: after the station is placed and a few poses judged
CELL = [
    "speed:=3.0",
    "dwell_s:=0.4",
    "tracker_rate_hz:=500.0",
    "base_to_tracker_xyz:=[2.4, -1.1, 0.35]",
    "base_to_tracker_rpy:=[0.01, -0.02, 2.2]",
    "flange_to_target_xyz:=[0.03, 0.02, 0.08]",
    "flange_to_target_rpy:=[0.3, 0.1, -0.5]",
    f"slip:=[1.0, 0.001, {SLIP_AFTER_S}]",
]


def monitor_statuses(received: list[DiagnosticArray]) -> list[tuple[int, dict[str, str]]]:
    return [
        (status.level, {kv.key: kv.value for kv in status.values})
        for msg in received
        for status in msg.status
        if status.name.endswith("tracker monitor")
    ]


def test_the_node_places_the_station_judges_the_still_poses_and_warns_of_a_slipped_joint(trained, tmp_path):
    rclpy.init()
    cell_args = [arg for value in CELL for arg in ("-p", value)]
    sim = start(
        "sim_cell_node", "--params-file", str(CONFIG_DIR / "sim_cell.yaml"), *cell_args, log=tmp_path / "sim.log"
    )
    node = start(
        "kinematics_node",
        "-p", f"model_dir:={trained[0]}",
        "-p", "monitor_tracker_topic:=/tracker/pose",
        "-p", "monitor_reference_poses:=10",
        "-p", "publish_corrected_pose:=false",
        "-p", "diagnostics_period_s:=0.5",
        log=tmp_path / "node.log",
    )  # fmt: skip
    client = Client("monitor_test_client")
    received: list[DiagnosticArray] = []
    client.node.create_subscription(DiagnosticArray, "/diagnostics", received.append, 100)
    try:
        deadline = time.monotonic() + 240.0
        while time.monotonic() < deadline and not any(
            level == DiagnosticStatus.WARN for level, _ in monitor_statuses(received)
        ):
            client.spin_for(0.2)
        statuses = monitor_statuses(received)
        first_warn = next(k for k, (level, _) in enumerate(statuses) if level == DiagnosticStatus.WARN)
    finally:
        client.close()
        assert stop(node) == 0, (tmp_path / "node.log").read_text()
        assert stop(sim) == 0, (tmp_path / "sim.log").read_text()
        rclpy.shutdown()
    states = [values["state"] for _, values in statuses]
    assert "placing" in states[:first_warn]
    judged_ok = [v for level, v in statuses[:first_warn] if v["state"] == "ok" and int(v["judged"]) > 0]
    assert judged_ok and judged_ok[0]["station"].startswith("placed from 10")
    assert statuses[first_warn][1]["state"] == "drifted"
    assert "DRIFTED" in (tmp_path / "node.log").read_text()
