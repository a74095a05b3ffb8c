"""The recorder's fast PoseStamped decoder against rclpy's own serialiser."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import serialize_message

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.raw_bag import decode_pose_stamped


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
