"""Crash-tolerant recording into a rosbag2 MCAP bag, and reading raw recordings back.

The recorder writes serialised messages straight into an MCAP file (chunked, so a killed process loses
at most the chunk in progress) and writes ``metadata.yaml`` when it opens the bag and again when it
closes it. Reading goes through the ``mcap`` stream reader, which returns everything up to a truncated
tail, so a bag left by SIGKILL reads back all its complete chunks.
"""

from __future__ import annotations

import os
import struct
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import yaml
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.pairs import (
    JOINT_STATE,
    JOINTS_TOPIC,
    POSE_STAMPED,
    POSE_TOPIC,
    TYPESTORE,
    Pairs,
    joint_state_msg,
    pose_stamped_msg,
)
from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix

CHUNK_BYTES = 256 * 1024  # about 1 s of 3 kHz poses: what a SIGKILL can cost
_STAMP_AND_FRAME_LEN = struct.Struct("<iII")
_POSE = struct.Struct("<7d")


def decode_pose_stamped(data: bytes) -> tuple[int, str, tuple[float, ...]]:
    """``(stamp_ns, frame_id, (x, y, z, qx, qy, qz, qw))`` from a little-endian CDR PoseStamped.

    At 3 kHz the generic deserialisers (about 20 µs a message) cost more than everything else the
    recorder does; the layout is fixed apart from the frame_id, so a struct read does it in about 1 µs.
    """
    if len(data) < 16 or data[1] != 1:  # encapsulation CDR_LE; ROS 2 publishers on x86 and ARM use it
        raise DataError(f"not a little-endian CDR PoseStamped ({len(data)} bytes, header {bytes(data[:4]).hex()})")
    sec, nanosec, n = _STAMP_AND_FRAME_LEN.unpack_from(data, 4)
    start = 4 + ((12 + n + 7) & ~7)  # the doubles are 8-aligned relative to the CDR body after the 4-byte header
    if n == 0 or start + _POSE.size > len(data):
        raise DataError(f"truncated CDR PoseStamped ({len(data)} bytes, frame_id of {n} bytes)")
    frame = bytes(data[16 : 16 + n - 1]).decode()
    return sec * 1_000_000_000 + nanosec, frame, _POSE.unpack_from(data, start)


class BagWriter:
    """A rosbag2 bag (MCAP storage) written message by message. Use as a context manager."""

    def __init__(self, path: str | Path, chunk_bytes: int = CHUNK_BYTES) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise DataError(f"{self.path} exists already, not overwriting")
        try:
            self.path.mkdir(parents=True)
            self.file: BinaryIO = open(self.path / f"{self.path.name}_0.mcap", "wb")  # noqa: SIM115
        except OSError as exc:
            raise DataError(f"cannot create bag {self.path}: {exc.strerror}") from exc
        self.writer = Writer(self.file, chunk_size=chunk_bytes, compression=CompressionType.NONE)
        self.writer.start(profile="ros2", library="hybrid_kinematics_ros")
        self.channels: dict[str, tuple[int, str]] = {}
        self.schemas: dict[str, int] = {}
        self.counts: Counter = Counter()
        self.first_ns: int | None = None
        self.last_ns = 0
        self.closed = False
        self.custom_data: dict[str, str] = {"writer": "hybrid_kinematics_ros"}
        self.sync_metadata()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic in self.channels:
            return
        if msgtype not in self.schemas:
            text, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
            self.schemas[msgtype] = self.writer.register_schema(msgtype, "ros2msg", text.encode())
        channel = self.writer.register_channel(topic, "cdr", self.schemas[msgtype])
        self.channels[topic] = (channel, msgtype)
        self.sync_metadata()

    def write(self, topic: str, time_ns: int, data: bytes) -> None:
        """Write one serialised (CDR) message; ``time_ns`` is the receive time, as rosbag2 records it."""
        try:
            self.writer.add_message(self.channels[topic][0], time_ns, bytes(data), time_ns)
        except OSError as exc:
            raise DataError(f"cannot write to {self.path}: {exc.strerror}; the data written so far is kept") from exc
        self.counts[topic] += 1
        self.first_ns = time_ns if self.first_ns is None else min(self.first_ns, time_ns)
        self.last_ns = max(self.last_ns, time_ns)

    def write_msg(self, topic: str, time_ns: int, msg: object) -> None:
        self.write(topic, time_ns, TYPESTORE.serialize_cdr(msg, self.channels[topic][1]))

    def flush(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.finish()
            self.file.close()
        finally:
            self.sync_metadata()

    def sync_metadata(self) -> None:
        write_metadata(
            self.path,
            f"{self.path.name}_0.mcap",
            {t: (m, self.counts[t]) for t, (_, m) in self.channels.items()},
            self.first_ns or 0,
            self.last_ns,
            self.custom_data,
        )


def write_metadata(
    path: Path,
    mcap_name: str,
    topics: dict[str, tuple[str, int]],
    start: int,
    end: int,
    custom_data: dict[str, str] | None = None,
) -> None:
    """rosbag2's ``metadata.yaml`` (version 9), as ``ros2 bag info`` and rosbags read it."""
    total = sum(count for _, count in topics.values())
    duration = max(0, end - start)
    info = {
        "rosbag2_bagfile_information": {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [mcap_name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": total,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": [],
                        "type_description_hash": "",
                    },
                    "message_count": count,
                }
                for topic, (msgtype, count) in topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": mcap_name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": total,
                }
            ],
            "custom_data": dict(custom_data or {}),
            "ros_distro": "jazzy",
        }
    }
    tmp = path / "metadata.yaml.tmp"
    tmp.write_text(yaml.safe_dump(info, sort_keys=False))
    tmp.replace(path / "metadata.yaml")


@dataclass
class RawRecording:
    """Decoded raw streams: stamps in ns (``header.stamp``), joints in the first message's name order."""

    joint_stamps: np.ndarray
    joint_names: tuple[str, ...]
    q: np.ndarray
    pose_stamps: np.ndarray
    pose_frame: str
    positions: np.ndarray
    quats: np.ndarray
    truncated: bool
    counts: Counter


def iter_messages(path: str | Path):
    """``(topic, msgtype, log_time, data)`` of every complete message; stops quietly at a truncated tail.

    Returns a generator; its ``truncated`` state is reported through :func:`read_raw`.
    """
    path = Path(path)
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    if not files:
        raise DataError(f"{path} holds no .mcap file")
    for file in files:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        with open(file, "rb") as f:
            try:
                for record in StreamReader(f, skip_magic=False).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message):
                        ch = channels[record.channel_id]
                        yield ch.topic, schemas[ch.schema_id].name, record.log_time, record.data
            except (McapError, EOFError, ValueError, KeyError) as exc:
                yield "__truncated__", str(exc), 0, b""


def read_raw(path: str | Path, joints_topic: str, pose_topic: str) -> RawRecording:
    joint_t, q, names = [], [], None
    pose_t, pose, frames = [], [], set()
    counts: Counter = Counter()
    truncated = False
    for topic, msgtype, _, data in iter_messages(path):
        if topic == "__truncated__":
            truncated = True
            continue
        counts[topic] += 1
        if topic == joints_topic and msgtype == JOINT_STATE:
            msg = TYPESTORE.deserialize_cdr(data, msgtype)
            if names is None:
                names = tuple(msg.name)
            if tuple(msg.name) != names:
                index = {n: i for i, n in enumerate(msg.name)}
                if any(n not in index for n in names):
                    counts["joint_state_other_joints"] += 1
                    continue
                position = [msg.position[index[n]] for n in names]
            else:
                position = msg.position
            joint_t.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            q.append(np.asarray(position, dtype=float))
        elif topic == pose_topic and msgtype == POSE_STAMPED:
            stamp, frame, values = decode_pose_stamped(data)
            pose_t.append(stamp)
            pose.append(values)
            frames.add(frame)
    if not joint_t or not pose_t:
        raise DataError(
            f"bag {path}: needs messages on {joints_topic} and {pose_topic}; found {dict(counts) or 'none'}"
        )
    if len(frames) > 1:
        raise DataError(f"bag {path}: {pose_topic} comes in several frames {sorted(frames)}")
    jt, pt = np.array(joint_t, dtype=np.int64), np.array(pose_t, dtype=np.int64)
    jo, po = np.argsort(jt, kind="stable"), np.argsort(pt, kind="stable")
    pose_values = np.array(pose)[po]
    return RawRecording(
        jt[jo], names, np.array(q)[jo], pt[po], frames.pop(), pose_values[:, :3], pose_values[:, 3:], truncated, counts
    )


def write_pairs_into(writer: BagWriter, pairs: Pairs) -> None:
    """Append calibration pairs (the contract's two topics) to an open bag."""
    writer.add_topic(JOINTS_TOPIC, JOINT_STATE)
    writer.add_topic(POSE_TOPIC, POSE_STAMPED)
    positions, quats = pose_from_matrix(pairs.T)
    if pairs.position_only:
        quats = np.zeros_like(quats)  # the contract's "no orientation"
    for q, p, quat, ns in zip(pairs.q, positions, quats, pairs.stamps, strict=True):
        ns = int(ns)
        writer.write_msg(JOINTS_TOPIC, ns, joint_state_msg(ns, pairs.joint_names, q))
        writer.write_msg(POSE_TOPIC, ns, pose_stamped_msg(ns, pairs.frame_id, p, quat))
    writer.sync_metadata()
