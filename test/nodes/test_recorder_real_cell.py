"""The recorder against a simulated cell that looks like a real one: a tracker standing in its own frame,
a plain reflector, noisy encoders, a best-effort driver. One simulated cell per test (they share topics)."""

from __future__ import annotations

import ast
import json
import re
import resource
import shutil
import signal
import subprocess
import time
from collections import Counter

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from hybrid_kinematics_ros.io.pairs import read_pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR, load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot
from test.nodes.rosutil import STARTED, Client, executable, start, stop

pytestmark = pytest.mark.ros
OFFSET = 0.0123
PLACED = [
    "-p",
    "base_to_tracker_xyz:=[2.4, -1.1, 0.35]",
    "-p",
    "base_to_tracker_rpy:=[0.01, -0.02, 2.2]",
    "-p",
    "flange_to_target_xyz:=[0.03, 0.02, 0.08]",
    "-p",
    "flange_to_target_rpy:=[0.3, 0.1, -0.5]",
]


@pytest.fixture
def client():
    rclpy.init()
    c = Client("real_cell_test_client")
    yield c
    c.close()
    rclpy.shutdown()


def record(client, tmp_path, name: str, seconds: float, sim_args=(), recorder_args=(), kill_when: str = ""):
    """Run a sim cell and a recorder for ``seconds`` of received poses, stop with SIGINT; return the
    recorder's diagnostics (key-values, level and message, while recording), the bag's metadata and the
    recorder's log. ``kill_when``: SIGKILL the recorder once its log shows this text after the SIGINT."""
    sim = start(
        "sim_cell_node",
        "--params-file",
        str(CONFIG_DIR / "sim_cell.yaml"),
        "-p",
        f"tracker_clock_offset_s:={OFFSET}",
        *sim_args,
        log=tmp_path / "sim.log",
    )
    node = f"recorder_{name}"

    def launch():
        shutil.rmtree(tmp_path / name, ignore_errors=True)  # what a restart's predecessor began
        args = ["-r", f"__node:={node}", "-p", f"output_dir:={tmp_path}", "-p", f"bag_name:={name}"]
        return start("recorder_node", *args, *recorder_args, log=tmp_path / f"{name}.log")

    proc, _ = client.service_of(launch(), Trigger, f"/{node}/stop", launch)  # up
    try:
        diagnostics = []
        sub = client.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)

        def ours():
            return [
                ({kv.key: kv.value for kv in s.values}, s.level, s.message)
                for m in diagnostics
                for s in m.status
                if s.name == node and s.message != "idle"
            ]

        def received() -> int:
            return max((int(d.get("tracker_poses", 0)) for d, _, _ in ours()), default=0)

        deadline = time.monotonic() + seconds * 4 + 60
        while received() < seconds * 3000 * 0.9 and time.monotonic() < deadline:
            client.spin_for(0.5)
        client.node.destroy_subscription(sub)
        if kill_when:
            log = tmp_path / f"{name}.log"
            proc.send_signal(signal.SIGINT)
            stopping = time.monotonic() + 120  # a recorder that never gets there fails, not hangs the suite
            while kill_when not in log.read_text() and proc.poll() is None and time.monotonic() < stopping:
                time.sleep(0.01)
            assert kill_when in log.read_text(), log.read_text()
            proc.kill()
            proc.wait()
        else:
            assert stop(proc, signal.SIGINT, timeout=120) == 0, (tmp_path / f"{name}.log").read_text()
    finally:
        stop(proc)
        stop(sim)
    meta = yaml.safe_load((tmp_path / name / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return ours(), meta, (tmp_path / f"{name}.log").read_text()


def align_cli(tmp_path, name: str, *extra: str) -> dict:
    out = tmp_path / f"{name}_pairs"
    command = ["hybrid-kinematics", "align", "--bag", str(tmp_path / name), "--out", str(out), "--robot", "ur10"]
    cli = subprocess.run([*command, *extra], capture_output=True, text=True, check=False)
    assert cli.returncode == 0, cli.stderr
    return json.loads(cli.stdout.strip().splitlines()[-1])


def test_tracker_in_its_own_frame_gives_the_offset_live_and_offline(client, tmp_path):
    _, meta, log = record(client, tmp_path, "placed", 30.0, PLACED)
    live = float(meta["custom_data"]["clock_offset_s"])
    assert abs(live - OFFSET) < 2e-4, log
    offline = align_cli(tmp_path, "placed")
    assert abs(offline["clock_offset_ms"] - 1e3 * OFFSET) < 0.2, offline
    assert offline["clock_skew_ppm"] == 0.0  # 30 s: too short to estimate a skew, none is claimed
    assert len(read_pairs(tmp_path / "placed_pairs")) > 0.5 * 30 * 110


def test_plain_reflector_is_recorded_and_aligned_position_only(client, tmp_path):
    _, meta, log = record(client, tmp_path, "plain", 25.0, ["-p", "plain_reflector:=true"])
    assert "clock_offset_s" in meta["custom_data"], log
    assert abs(float(meta["custom_data"]["clock_offset_s"]) - OFFSET) < 2e-4, log
    pairs = read_pairs(tmp_path / "plain")
    assert pairs.position_only and len(pairs) > 0.5 * 25 * 110
    offline = align_cli(tmp_path, "plain", "--offset-s", str(OFFSET))  # was an IndexError
    assert read_pairs(tmp_path / "plain_pairs").position_only
    # live used its estimate of the offset (within 0.2 ms), offline the exact one: a joint state at either
    # end of the tracker stream can fall inside with one and outside with the other
    assert abs(offline["pairs"] - len(pairs)) <= 2, (offline["pairs"], len(pairs))


def test_raw_data_is_final_before_the_alignment_and_pairs_share_its_time_base(client, tmp_path):
    # killed while it aligns (after a SIGTERM's grace period, say): the raw data is all there
    _, _, log = record(client, tmp_path, "killed", 15.0, kill_when="; aligning")
    said = ast.literal_eval(re.search(r"raw recording finalised \((\{.*?\})\)", log).group(1))
    reader = Reader(tmp_path / "killed")
    reader.open()
    found = Counter(c.topic for c, _, _ in reader.messages())
    assert reader.message_count == found.total() and {t: found[t] for t in said} == said, (found, said)
    reader.close()
    # stopped normally: a pair is logged when its joint state was received, in the raw topics' time base
    record(client, tmp_path, "timed", 10.0)
    reader = Reader(tmp_path / "timed")
    reader.open()
    received, logged = {}, []
    for conn, log_ns, raw in reader.messages():
        if conn.topic in ("/joint_states", "/calibration/joint_states"):
            stamp = deserialize_message(raw, JointState).header.stamp
            key = stamp.sec * 10**9 + stamp.nanosec
            (received.__setitem__(key, log_ns) if conn.topic == "/joint_states" else logged.append((key, log_ns)))
    assert logged and all(received[k] == t for k, t in logged)
    assert reader.start_time == min(received.values()) and reader.end_time >= max(received.values())
    reader.close()


def test_static_mode_with_noisy_quantised_encoders(client, tmp_path):
    encoder = ["-p", "encoder_noise_rad:=2e-6", "-p", f"encoder_resolution_rad:={2 * np.pi / 2**20!r}"]
    _, meta, log = record(
        client,
        tmp_path,
        "static",
        20.0,
        [*encoder, "-p", "speed:=1.0"],  # moves of 2-4 s: about 5 dwells of 0.3 s in 20 s
        ["-p", "static_min_s:=0.2", "-p", "max_joint_speed:=5.0", "-p", f"clock_offset_s:={OFFSET}"],
    )
    assert "pairs" in meta["custom_data"], log  # was: static mode: no still window
    pairs = read_pairs(tmp_path / "static")
    assert len(pairs) >= 3 and len(pairs) == int(meta["custom_data"]["pairs"])
    cfg = load_robot_config("ur10")
    pos, _ = se3.pose_errors(pairs.T, TrueRobot.from_config(cfg).fk(pairs.q))
    assert np.mean(pos) < 0.02, pos  # mm: a still window's average


def test_many_beam_breaks_warn(client, tmp_path):
    # the sim breaks the beam once a second for 0.2 s; the default threshold is 6 a minute
    status, _, _ = record(client, tmp_path, "breaks", 12.0, ["-p", "dropout_rate_hz:=1.0"])
    warned = [message for _, level, message in status if level == DiagnosticStatus.WARN and "beam" in message]
    assert warned, status[-3:]


def test_best_effort_tracker_driver_is_recorded(client, tmp_path):
    """A driver publishing best-effort: a reliable-only subscription never matched it."""

    def launch():
        shutil.rmtree(tmp_path / "be", ignore_errors=True)  # what a restart's predecessor began
        args = ["-r", "__node:=recorder_be", "-p", f"output_dir:={tmp_path}", "-p", "bag_name:=be"]
        return start("recorder_node", *args, log=tmp_path / "be.log")

    proc, _ = client.service_of(launch(), Trigger, "/recorder_be/stop", launch)
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    pose_pub = client.node.create_publisher(PoseStamped, "/tracker/pose", best_effort)
    joint_pub = client.node.create_publisher(JointState, "/joint_states", 10)

    def publish() -> None:
        stamp = client.node.get_clock().now().to_msg()
        pose = PoseStamped()
        pose.header.stamp, pose.header.frame_id = stamp, "tracker"
        pose.pose.orientation.w = 1.0
        pose_pub.publish(pose)
        joints = JointState(name=list(load_robot_config("ur10").chain.joint_names), position=[0.0] * 6)
        joints.header.stamp = stamp
        joint_pub.publish(joints)

    timer = client.node.create_timer(0.01, publish)
    try:
        diagnostics = []
        sub = client.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)

        def poses() -> int:
            ours = [kv for m in diagnostics for s in m.status if s.name == "recorder_be" for kv in s.values]
            return max((int(kv.value) for kv in ours if kv.key == "tracker_poses"), default=0)

        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and poses() < 100:
            client.spin_for(0.5)
        client.node.destroy_subscription(sub)
    finally:
        client.node.destroy_timer(timer)
        assert stop(proc) == 0
    counts = received_counts(tmp_path / "be")
    assert counts.get("/tracker/pose", 0) > 50 and counts.get("/joint_states", 0) > 50, counts


def received_counts(bag) -> dict:
    """Messages per topic that metadata.yaml says the bag holds (rewritten with every chunk)."""
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}


def test_a_write_failure_is_an_error_and_the_recorder_keeps_serving(client, tmp_path):
    """A file size limit (as a full disk would) makes the bag unwritable after about 3 MB."""
    limit = 3 * 2**20
    log = tmp_path / "full.log"
    command = [str(executable("recorder_node")), "--ros-args", "-r", "__node:=recorder_full"]
    command += ["-p", f"output_dir:={tmp_path}", "-p", "bag_name:=full"]
    sim = start("sim_cell_node", "--params-file", str(CONFIG_DIR / "sim_cell.yaml"), log=tmp_path / "sim.log")
    with open(log, "w") as out:
        proc = subprocess.Popen(
            command,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)),
        )
    STARTED.append(proc)
    try:
        stop_srv = client.service(Trigger, "/recorder_full/stop")
        diagnostics = []
        sub = client.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
        deadline = time.monotonic() + 90.0
        errors: list = []
        while not errors and time.monotonic() < deadline:
            client.spin_for(0.5)
            errors = [
                s
                for m in diagnostics
                for s in m.status
                if s.name == "recorder_full" and s.level == DiagnosticStatus.ERROR
            ]
        client.node.destroy_subscription(sub)
        assert errors and "write failed" in errors[-1].message, log.read_text()
        answer = client.call(stop_srv, Trigger.Request(), timeout=60, resend_after=60)
        assert answer.success, answer.message  # still serving
    finally:
        stop(proc)
        stop(sim)
    reader = Reader(tmp_path / "full")  # what was written before the failure is a valid bag
    reader.open()
    assert reader.message_count == sum(1 for _ in reader.messages()) > 3000
    reader.close()
