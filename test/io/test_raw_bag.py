"""The recorder's fast PoseStamped decoder against rclpy's own serialiser."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.pairs import Pairs, pose_stamped_msg
from hybrid_kinematics_ros.io.raw_bag import BagWriter, decode_pose_stamped, iter_messages, read_raw, write_pairs_into


@pytest.mark.parametrize("frame", ["", "t", "ab", "tracker", "tracker1", "laser_tracker_frame_at_the_cell"])
def test_decoder_matches_rclpy_for_every_frame_alignment(frame):
    rng = np.random.default_rng(len(frame))
    for _ in range(20):
        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.header.stamp.sec = int(rng.integers(0, 2**31 - 1))
        msg.header.stamp.nanosec = int(rng.integers(0, 10**9))
        values = rng.normal(size=7)
        p, o = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z, o.x, o.y, o.z, o.w = values.tolist()
        stamp, decoded_frame, decoded = decode_pose_stamped(serialize_message(msg))
        assert stamp == msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert decoded_frame == frame
        assert decoded == tuple(values.tolist())  # bit for bit


def test_truncated_or_big_endian_data_is_refused():
    msg = PoseStamped()
    msg.header.frame_id = "tracker"
    raw = serialize_message(msg)
    with pytest.raises(DataError, match="truncated"):
        decode_pose_stamped(raw[:-8])
    with pytest.raises(DataError, match="little-endian"):
        decode_pose_stamped(raw[:1] + b"\x00" + raw[2:])


WRITER = """
import os, signal, sys
import numpy as np
from hybrid_kinematics_ros.io.pairs import JOINT_STATE, POSE_STAMPED, joint_state_msg, pose_stamped_msg
from hybrid_kinematics_ros.io.raw_bag import BagWriter

writer = BagWriter(sys.argv[1], chunk_bytes=16384, file_chunks=int(sys.argv[2]))
writer.add_topic("/joint_states", JOINT_STATE)
writer.add_topic("/tracker/pose", POSE_STAMPED)
for i in range(20057):
    ns = 1_700_000_000_000_000_000 + i * 1_000_000
    if i % 10 == 0:
        writer.write_msg("/joint_states", ns, joint_state_msg(ns, ["a", "b"], np.array([0.1, i])))
    pose = pose_stamped_msg(ns, "tracker", np.array([i, 0.0, 0.0]), np.array([0, 0, 0, 1.0]))
    writer.write_msg("/tracker/pose", ns, pose)
os.kill(os.getpid(), signal.SIGKILL)  # between two messages, mid-chunk: deterministic
"""


@pytest.mark.parametrize("file_chunks", [1000, 7])
def test_a_sigkilled_bag_reads_with_its_real_message_count(tmp_path, file_chunks):
    """Killed mid-recording, the bag opens in rosbags and the mcap library (its files used to end without
    a footer, which both refuse), and metadata.yaml counts what the files hold, also across split files."""
    bag = tmp_path / "killed"
    proc = subprocess.run([sys.executable, "-c", WRITER, str(bag), str(file_chunks)], check=False)
    assert proc.returncode == -signal.SIGKILL
    reader = Reader(bag)
    reader.open()
    counted = Counter(c.topic for c, _, _ in reader.messages())
    assert reader.message_count == counted.total() >= 22063 - 300  # all but the chunk in progress
    reader.close()
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    in_files = 0
    for entry in meta["files"]:
        with open(bag / entry["path"], "rb") as f:
            n = sum(1 for _ in make_reader(f).iter_messages())
        assert n == entry["message_count"]
        in_files += n
    assert in_files == counted.total() and (len(meta["files"]) > 2) == (file_chunks == 7)
    raw = read_raw(bag, "/joint_states", "/tracker/pose")
    assert len(raw.pose_stamps) + len(raw.joint_stamps) >= counted.total()  # plus a started file's messages


def test_pairs_added_mid_chunk_keep_every_raw_message(tmp_path):
    """The recorder writes each segment's pairs while the raw streams go on, so the pair topics are added
    in the middle of a chunk: that used to hand the chunk's messages to the trailer's throwaway copy of
    the writer, and the file could not be read past that point (a 2.5-minute live run kept 63 % of it)."""
    writer = BagWriter(tmp_path / "mid")
    writer.add_topic("/tracker/pose", "geometry_msgs/msg/PoseStamped")
    names = ("a", "b")
    for i in range(3000):
        ns = 1_700_000_000_000_000_000 + i * 1_000_000
        writer.write_msg("/tracker/pose", ns, pose_stamped_msg(ns, "tracker", np.array([i, 0.0, 0.0]), [0, 0, 0, 1]))
        if i in (1000, 2000):  # mid-chunk (a chunk holds about 2,600 of these)
            stamps = ns + np.arange(3)
            write_pairs_into(writer, Pairs(np.zeros((3, 2)), np.tile(np.eye(4), (3, 1, 1)), stamps, names, "base"))
    writer.close()
    read = Counter(topic for topic, *_ in iter_messages(tmp_path / "mid"))
    assert read == writer.counts, (read, writer.counts)
    reader = Reader(tmp_path / "mid")
    reader.open()
    assert reader.message_count == sum(1 for _ in reader.messages()) == 3012
    reader.close()


def test_joints_are_taken_by_name_from_any_message_that_has_them_all(tmp_path):
    """A gripper joint first in every message, the arm's joints in another order, and a driver that also
    publishes a message with the gripper alone: the chain's joints come out by name, the partial messages
    are counted, none is read as the arm (the first message's names used to define the recording)."""
    from hybrid_kinematics_ros.io.pairs import JOINT_STATE, POSE_STAMPED, joint_state_msg

    writer = BagWriter(tmp_path / "gripper")
    writer.add_topic("/joint_states", JOINT_STATE)
    writer.add_topic("/tracker/pose", POSE_STAMPED)
    arm = ("j1", "j2", "j3")
    for i in range(50):
        ns = 1_700_000_000_000_000_000 + i * 10_000_000
        writer.write_msg("/joint_states", ns, joint_state_msg(ns, ["finger"], np.array([0.04])))
        q = np.array([0.1 * i, -0.2 * i, 0.3])
        writer.write_msg(
            "/joint_states", ns, joint_state_msg(ns, ["finger", "j3", "j1", "j2"], np.r_[0.04, q[[2, 0, 1]]])
        )
        writer.write_msg("/tracker/pose", ns, pose_stamped_msg(ns, "tracker", np.zeros(3), np.array([0, 0, 0, 1.0])))
    writer.close()
    raw = read_raw(tmp_path / "gripper", "/joint_states", "/tracker/pose", arm)
    assert raw.joint_names == arm and raw.q.shape == (50, 3)
    np.testing.assert_array_equal(raw.q[:, 0], 0.1 * np.arange(50))
    np.testing.assert_array_equal(raw.q[:, 1], -0.2 * np.arange(50))
    assert raw.counts["joint_state_other_joints"] == 50
    with pytest.raises(DataError, match="joint states with all of j1, j2, j9"):
        read_raw(tmp_path / "gripper", "/joint_states", "/tracker/pose", ("j1", "j2", "j9"))
