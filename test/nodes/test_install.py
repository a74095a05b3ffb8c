"""The README's workspace build, without ``--symlink-install``: the package lands in site-packages and its
files in the share directory. Each executable starts from that install, in an environment that knows
nothing of this checkout, from a directory other than the sources."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from std_srvs.srv import Trigger

from hybrid_kinematics_interfaces.srv import ComputeFK
from hybrid_kinematics_ros.kinematics.fk import fk_single
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.nodes.convert import joint_state_msg
from test.nodes.rosutil import ROOT, Client, start_command, stop

pytestmark = pytest.mark.ros
# what a clone holds that the build does not need; the build must not see this checkout's own outputs
NOT_SOURCES = (".git", ".venv", "build", "install", "log", "bags", "out", "__pycache__", ".pytest_cache", "env.sh")
SHARE = Path("install/hybrid_kinematics_ros/share/hybrid_kinematics_ros")
LIB = Path("install/hybrid_kinematics_ros/lib/hybrid_kinematics_ros")


def clean_env() -> dict[str, str]:
    """This process's environment without this checkout's install: only the venv's ROS (as bootstrap.sh
    builds with), so that the workspace's own setup.sh decides what is found."""
    env = dict(os.environ)
    for key in ("PATH", "PYTHONPATH", "LD_LIBRARY_PATH"):
        # the checkout's install goes; the venv stays, also where it lives inside the checkout (as in CI)
        parts = [
            p
            for p in env.get(key, "").split(os.pathsep)
            if p and (not p.startswith(str(ROOT)) or p.startswith(sys.prefix))
        ]
        env[key] = os.pathsep.join(parts)
    env.pop("COLCON_PREFIX_PATH", None)
    env["AMENT_PREFIX_PATH"] = env["CMAKE_PREFIX_PATH"] = sys.prefix
    return env


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """Build once: ``~/ws/src/hybrid_kinematics_ros`` with scripts/bootstrap.sh's flags minus symlinks."""
    ws = tmp_path_factory.mktemp("ws")
    shutil.copytree(ROOT, ws / "src" / "hybrid_kinematics_ros", ignore=shutil.ignore_patterns(*NOT_SOURCES))
    build = subprocess.run(
        [
            "colcon",
            "--log-base",
            "log",
            "build",
            "--event-handlers",
            "console_direct-",
            "--base-paths",
            "src/hybrid_kinematics_ros",
            "src/hybrid_kinematics_ros/hybrid_kinematics_interfaces",
            "--cmake-args",
            f"-DPython3_EXECUTABLE={sys.executable}",
            "-DBUILD_TESTING=OFF",
        ],
        cwd=ws,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert not (ws / LIB / "kinematics_node").is_symlink()
    rclpy.init()
    client = Client("install_test_client")
    yield ws, client
    client.close()
    rclpy.shutdown()


def in_workspace(ws: Path, *argv: str) -> list[str]:
    """``. install/setup.sh && exec argv``: how a user runs anything from the workspace."""
    return ["bash", "-c", '. "$0/install/setup.sh" && exec "$@"', str(ws), *argv]


def test_installed_package_finds_its_files_in_share(workspace):
    ws, _ = workspace
    code = (
        "import hybrid_kinematics_ros, sys; from hybrid_kinematics_ros.kinematics.paths import config_dir; "
        "from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config as load; "
        "print(hybrid_kinematics_ros.__file__); print(config_dir()); "
        "print(load('ur10').urdf_path); print(load('package://hybrid_kinematics_ros/config/rx160.yaml').name)"
    )
    out = subprocess.run(
        in_workspace(ws, sys.executable, "-c", code), cwd=ws, env=clean_env(), capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    module, config, urdf, rx160 = out.stdout.split()
    assert Path(module).is_relative_to(ws / "install") and "site-packages" in module
    assert Path(config) == ws / SHARE / "config" and Path(urdf) == ws / SHARE / "config" / "ur10.urdf"
    assert rx160 == "rx160"


def test_installed_cli_imports_with_a_shipped_spec(workspace, tmp_path):
    """``import --spec <shipped name>`` from the plain install: the spec is found in share, not next to
    the installed modules (it was looked up through ``__file__`` and found nothing)."""
    ws, _ = workspace
    excerpt = Path(__file__).resolve().parents[1] / "fixtures" / "ipa-robot-accuracy"
    csv = excerpt / "Series_A_measurements_grid_head40.csv"
    command = [str(ws / LIB / "hybrid-kinematics"), "import", "--spec", "ipa_robot_accuracy_a"]
    command += ["--robot", "ur10", "--csv", str(csv), "--out", str(tmp_path / "a")]
    out = subprocess.run(in_workspace(ws, *command), cwd=ws, env=clean_env(), capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "imported 40 of 40 rows" in out.stderr


def test_kinematics_node_with_the_readme_params_file(workspace):
    """The README's run from ``~/ws``: the params file gives the URDF as a package:// path."""
    ws, client = workspace
    params = ws / "src" / "hybrid_kinematics_ros" / "config" / "kinematics.yaml"
    log = ws / "kinematics_node.log"
    proc = start_command(
        in_workspace(ws, str(ws / LIB / "kinematics_node"), "--ros-args", "--params-file", str(params)),
        log=log,
        cwd=ws,
        env=clean_env(),
    )
    try:
        fk = client.service(ComputeFK, "/kinematics_node/compute_fk")
        chain = load_robot_config("ur10").chain
        req = ComputeFK.Request()
        req.joint_states = [joint_state_msg(np.zeros(6), chain.joint_names, rclpy.time.Time().to_msg())]
        resp = client.call(fk, req)
        assert resp.success, resp.message
        p = resp.poses[0].pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], fk_single(chain, np.zeros(6))[:3, 3], atol=1e-12)
    finally:
        assert stop(proc) == 0, log.read_text()


def test_sim_cell_node_publishes_with_its_default_robot(workspace):
    ws, client = workspace
    log = ws / "sim_cell_node.log"
    proc = start_command(in_workspace(ws, str(ws / LIB / "sim_cell_node")), log=log, cwd=ws, env=clean_env())
    poses = []
    sub = client.node.create_subscription(PoseStamped, "/tracker/pose", poses.append, 100)
    try:
        deadline = time.monotonic() + 120.0
        while not poses and time.monotonic() < deadline and proc.poll() is None:
            client.spin_for(0.1)
        assert poses, log.read_text()
    finally:
        client.node.destroy_subscription(sub)
        assert stop(proc) == 0, log.read_text()


def test_recorder_node_serves_with_its_default_robot(workspace):
    ws, client = workspace
    log = ws / "recorder_node.log"
    argv = in_workspace(
        ws, str(ws / LIB / "recorder_node"), "--ros-args", "-p", "autostart:=false", "-p", f"output_dir:={ws / 'bags'}"
    )
    proc = start_command(argv, log=log, cwd=ws, env=clean_env())
    try:
        start_srv = client.service(Trigger, "/recorder_node/start")
        assert start_srv.service_is_ready(), log.read_text()
    finally:
        assert stop(proc) == 0, log.read_text()
