"""The calibration-pairs bag contract: exact round trips, other people's bags, and malformed bags."""

from __future__ import annotations

import numpy as np
import pytest
from mcap_ros2.reader import read_ros2_messages
from rosbags.rosbag2 import StoragePlugin, Writer

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.pairs import (
    JOINT_STATE,
    JOINTS_TOPIC,
    POSE_STAMPED,
    POSE_TOPIC,
    TYPESTORE,
    Pairs,
    PairsWriter,
    condition_msg,
    joint_state_msg,
    pose_stamped_msg,
    read_pairs,
    write_pairs,
)
from hybrid_kinematics_ros.kinematics import se3

NAMES = ("a", "b", "c")


def make_pairs(n=50, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3, 3, (n, 3))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    T = se3.matrix_from_pose(rng.uniform(-1, 1, (n, 3)), quat)
    stamps = 1_000_000_000 + 7_000_000 * np.arange(n, dtype=np.int64)
    return Pairs(q, T, stamps, NAMES, "base_link")


def test_round_trip_is_exact(tmp_path):
    pairs = make_pairs()
    write_pairs(tmp_path / "bag", pairs)
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    back = read_pairs(tmp_path / "bag")
    np.testing.assert_array_equal(back.q, pairs.q)
    np.testing.assert_array_equal(back.stamps, pairs.stamps)
    np.testing.assert_allclose(back.T, pairs.T, atol=1e-15)
    assert back.joint_names == NAMES and back.frame_id == "base_link" and not back.dropped


def test_mcap_library_reads_our_bag(tmp_path):
    write_pairs(tmp_path / "bag", make_pairs(10))
    mcap_file = next((tmp_path / "bag").glob("*.mcap"))
    msgs = list(read_ros2_messages(str(mcap_file)))
    assert len(msgs) == 20
    assert {m.channel.topic for m in msgs} == {JOINTS_TOPIC, POSE_TOPIC}


def write_raw(path, entries):
    """A bag written with rosbags alone from standard types, the way other tools write them."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            JOINTS_TOPIC: writer.add_connection(JOINTS_TOPIC, JOINT_STATE, typestore=TYPESTORE),
            POSE_TOPIC: writer.add_connection(POSE_TOPIC, POSE_STAMPED, typestore=TYPESTORE),
        }
        for bag_time, (topic, msg) in enumerate(entries):
            writer.write(conns[topic], 5 + bag_time, TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def test_foreign_bag_with_shuffled_joint_order_and_bag_times(tmp_path):
    q = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    entries = []
    for i, qi in enumerate(q):
        ns = 10**9 * (i + 1)
        # poses first, joint names in another order, bag time unrelated to header stamps
        entries.append((POSE_TOPIC, pose_stamped_msg(ns, "base_link", [i, 0, 0], [0, 0, 0, 1])))
        entries.append((JOINTS_TOPIC, joint_state_msg(ns, ("c", "a", "b"), qi[[2, 0, 1]])))
    write_raw(tmp_path / "bag", entries)
    pairs = read_pairs(tmp_path / "bag", joint_names=NAMES)
    np.testing.assert_array_equal(pairs.q, q)
    np.testing.assert_array_equal(pairs.T[:, 0, 3], [0, 1])


def test_bad_samples_are_dropped_and_counted(tmp_path):
    entries = []
    for i in range(6):
        ns = 10**9 * (i + 1)
        position = np.array([0.1, 0.2, np.nan if i == 1 else 0.3])
        quat = [0, 0, 0, 1.5] if i == 2 else [0, 0, 0, 1]
        if i != 3:
            entries.append((POSE_TOPIC, pose_stamped_msg(ns, "base_link", [0, 0, 0], quat)))
        entries.append((JOINTS_TOPIC, joint_state_msg(ns + (5 if i == 4 else 0), NAMES, position)))
    write_raw(tmp_path / "bag", entries)
    pairs = read_pairs(tmp_path / "bag")
    assert len(pairs) == 2
    assert pairs.dropped == {
        "nan_or_inf": 1,
        "non_unit_quaternion": 1,
        "joint_state_without_pose": 2,
        "pose_without_joint_state": 1,
    }


def test_malformed_bags_get_clear_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        read_pairs(tmp_path / "none")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "metadata.yaml").write_text("not: a bag\n")
    with pytest.raises(DataError, match="cannot open bag"):
        read_pairs(tmp_path / "junk")
    with Writer(tmp_path / "only_joints", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(JOINTS_TOPIC, JOINT_STATE, typestore=TYPESTORE)
        writer.write(conn, 1, TYPESTORE.serialize_cdr(joint_state_msg(1, NAMES, np.zeros(3)), JOINT_STATE))
    with pytest.raises(DataError, match="has no topic /calibration/tracker_pose"):
        read_pairs(tmp_path / "only_joints")
    write_pairs(tmp_path / "bag", make_pairs(5))
    with pytest.raises(DataError, match=r"unknown \['a', 'b', 'c'\], missing \['x', 'y', 'z'\]"):
        read_pairs(tmp_path / "bag", joint_names=("x", "y", "z"))
    with pytest.raises(DataError, match="exists already"):
        write_pairs(tmp_path / "bag", make_pairs(5))


def test_condition_channels_round_trip_subset_and_concatenate(tmp_path):
    pairs = make_pairs(20)
    temperature = 22.9 + 0.01 * np.arange(20)
    pairs.conditions["temperature"] = temperature
    write_pairs(tmp_path / "bag", pairs)
    mcap_file = next((tmp_path / "bag").glob("*.mcap"))
    topics = {m.channel.topic: m.schema.name for m in read_ros2_messages(str(mcap_file))}
    assert topics["/calibration/temperature"] == "sensor_msgs/msg/Temperature"
    back = read_pairs(tmp_path / "bag")
    np.testing.assert_array_equal(back.conditions["temperature"], temperature)
    part = back.subset(np.array([3, 1]))
    np.testing.assert_array_equal(part.conditions["temperature"], temperature[[3, 1]])
    both = Pairs.concatenate([part, back])
    np.testing.assert_array_equal(both.conditions["temperature"], np.concatenate([temperature[[3, 1]], temperature]))
    # a channel only some parts carry cannot be an input for every sample: it is left out
    assert Pairs.concatenate([back, make_pairs(3)]).conditions == {}
    with pytest.raises(DataError, match=r"condition 'temperature' has shape \(2,\), expected \(20,\)"):
        Pairs(pairs.q, pairs.T, pairs.stamps, NAMES, "base_link", conditions={"temperature": np.zeros(2)})


def test_bag_without_conditions_reads_with_none_and_missing_values_are_dropped(tmp_path):
    entries = []
    for i in range(4):
        ns = 10**9 * (i + 1)
        entries.append((POSE_TOPIC, pose_stamped_msg(ns, "base_link", [i, 0, 0], [0, 0, 0, 1])))
        entries.append((JOINTS_TOPIC, joint_state_msg(ns, NAMES, np.zeros(3))))
    write_raw(tmp_path / "old", entries)  # the two topics only, as bags were before condition channels
    assert read_pairs(tmp_path / "old").conditions == {}

    pairs = make_pairs(4)
    with PairsWriter(tmp_path / "bag", NAMES, "base_link", conditions=["temperature"]) as writer:
        writer.write(pairs.q[:2], pairs.T[:2], pairs.stamps[:2], {"temperature": np.array([21.0, np.nan])})
        with pytest.raises(DataError, match=r"condition values for \[\], expected \['temperature'\]"):
            writer.write(pairs.q[2:], pairs.T[2:], pairs.stamps[2:])
    with Writer(tmp_path / "bag2", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [
            writer.add_connection(t, m, typestore=TYPESTORE)
            for t, m in (
                (JOINTS_TOPIC, JOINT_STATE),
                (POSE_TOPIC, POSE_STAMPED),
                ("/calibration/temperature", "sensor_msgs/msg/Temperature"),
            )
        ]
        for i, ns in enumerate(pairs.stamps):
            msgs = [joint_state_msg(ns, NAMES, pairs.q[i]), pose_stamped_msg(ns, "base_link", [0, 0, i], [0, 0, 0, 1])]
            if i < 2:  # the last two samples come without a temperature
                msgs.append(condition_msg(ns, "temperature", [21.0, np.nan][i]))
            for conn, msg in zip(conns, msgs, strict=False):
                writer.write(conn, int(ns), TYPESTORE.serialize_cdr(msg, conn.msgtype))
    for bag in ("bag", "bag2"):
        back = read_pairs(tmp_path / bag)
        assert len(back) == 1 and back.conditions["temperature"].tolist() == [21.0]
    assert back.dropped == {"without_temperature": 2, "nan_or_inf": 1}
