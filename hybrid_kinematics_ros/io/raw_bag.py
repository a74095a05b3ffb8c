"""Crash-tolerant recording into a rosbag2 MCAP bag, and reading raw recordings back.

The recorder writes serialised messages straight into MCAP files that are valid at every chunk
boundary (see :class:`BagWriter`), so a killed process loses at most the chunk in progress and leaves a
bag that any MCAP reader opens, with a ``metadata.yaml`` that counts what is in it. Reading goes through
the ``mcap`` stream reader, which also returns everything up to a truncated tail.

Why a writer of our own beside rosbags' (which writes the pairs bags): rosbags writes the MCAP summary and
``metadata.yaml`` only on close, so a recording SIGKILLed after hours would leave a bag that readers
refuse or count as empty. That is fine for an offline conversion, not for the recorder.
"""

from __future__ import annotations

import copy
import errno
import os
import struct
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from mcap.data_stream import RecordBuilder
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

    At 3 kHz the generic deserialisers cost more than everything else the recorder does; the layout is fixed
    apart from the frame_id, so a struct read does it for a small fraction of their cost.
    """
    if len(data) < 16 or data[1] != 1:  # encapsulation CDR_LE; ROS 2 publishers on x86 and ARM use it
        raise DataError(f"not a little-endian CDR PoseStamped ({len(data)} bytes, header {bytes(data[:4]).hex()})")
    sec, nanosec, n = _STAMP_AND_FRAME_LEN.unpack_from(data, 4)
    start = 4 + ((12 + n + 7) & ~7)  # the doubles are 8-aligned relative to the CDR body after the 4-byte header
    if n == 0 or start + _POSE.size > len(data):
        raise DataError(f"truncated CDR PoseStamped ({len(data)} bytes, frame_id of {n} bytes)")
    frame = bytes(data[16 : 16 + n - 1]).decode()
    return sec * 1_000_000_000 + nanosec, frame, _POSE.unpack_from(data, start)


class _Pending:
    """The stream the mcap Writer writes into: bytes wait here until :class:`BagWriter` commits them."""

    def __init__(self, base: int = 0) -> None:
        self.base = base  # file offset of the first pending byte
        self.buf = bytearray()

    def write(self, data: bytes) -> int:
        self.buf += data
        return len(data)

    def tell(self) -> int:
        return self.base + len(self.buf)

    def flush(self) -> None:
        pass


class BagWriter:
    """A rosbag2 bag (MCAP storage) written message by message, valid on disk at every chunk boundary.

    Each time the mcap Writer completes a chunk, the chunk goes to the file together with a summary and
    footer (what ``finish`` would write) in one ``pwrite``; the next chunk overwrites that trailer. So a
    SIGKILLed bag is a complete, indexed MCAP up to its last chunk, which rosbags and the mcap library
    read as they are, and ``metadata.yaml``, rewritten at the same moment, holds its real message count.
    The trailer lists every chunk of the file: files are split every ``file_chunks`` chunks (about 10
    minutes at 3 kHz) to keep it small. ``split()`` starts the next file at once (the recorder closes the
    raw data that way before it aligns). Use as a context manager.
    """

    def __init__(self, path: str | Path, chunk_bytes: int = CHUNK_BYTES, file_chunks: int = 600) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise DataError(f"{self.path} exists already, not overwriting")
        try:
            self.path.mkdir(parents=True)
        except OSError as exc:
            raise DataError(f"cannot create bag {self.path}: {exc.strerror}") from exc
        self.chunk_bytes, self.file_chunks = chunk_bytes, file_chunks
        self.topics: dict[str, str] = {}  # topic -> message type
        self.files: list[dict] = []  # per file: name, counts, first/last log time
        self.counts: Counter = Counter()
        self.first_ns: int | None = None
        self.last_ns = 0
        self.closed = False
        self.custom_data: dict[str, str] = {"writer": "hybrid_kinematics_ros"}
        self.fd = -1
        self._committed: tuple = (Counter(), [], None, 0)
        self._open_file()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _open_file(self) -> None:
        name = f"{self.path.name}_{len(self.files)}.mcap"
        try:
            self.fd = os.open(self.path / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except OSError as exc:
            raise DataError(f"cannot create {self.path / name}: {exc.strerror}") from exc
        self.files.append({"name": name, "counts": Counter(), "first": None, "last": 0, "chunks": 0})
        self.pending = _Pending()
        self.writer = Writer(self.pending, chunk_size=self.chunk_bytes, compression=CompressionType.NONE)
        self.writer.start(profile="ros2", library="hybrid_kinematics_ros")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        for topic, msgtype in self.topics.items():
            self._register(topic, msgtype)
        self._commit()

    def _register(self, topic: str, msgtype: str) -> None:
        if msgtype not in self.schemas:
            text, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
            self.schemas[msgtype] = self.writer.register_schema(msgtype, "ros2msg", text.encode())
        self.channels[topic] = self.writer.register_channel(topic, "cdr", self.schemas[msgtype])

    def _trailer(self) -> bytes:
        """What ``Writer.finish`` would append now, computed on a copy; the chunk builder must be empty (it is
        shared with the copy): right after a chunk, or after ``add_topic`` ended one."""
        copy_ = copy.copy(self.writer)
        out = _Pending(self.pending.tell())
        copy_._Writer__stream = out  # mcap has no public way to get the summary bytes before finish
        copy_._Writer__record_builder = RecordBuilder()
        copy_._Writer__summary_offsets = []
        copy_.finish()
        return bytes(out.buf)

    def _commit(self, final: bool = False) -> None:
        """Write the pending records (and, unless final, a trailer) where the last trailer began."""
        data = bytes(self.pending.buf) + (b"" if final else self._trailer())
        # metadata.yaml is prepared first and renamed into place right after the data: a kill can split
        # the two only within those microseconds (about 1e-5 of the time at one chunk a second)
        staged = self.sync_metadata(stage=True)
        try:
            # the space first: when the disk is full (or a size limit is hit) this fails and leaves the file
            # as it was, valid up to its last trailer; a short pwrite would have cut the trailer
            os.posix_fallocate(self.fd, self.pending.base, len(data))
            if os.pwrite(self.fd, data, self.pending.base) != len(data):
                raise OSError(errno.ENOSPC, "short write")
            if final:
                os.ftruncate(self.fd, self.pending.base + len(data))
            staged.replace(self.path / "metadata.yaml")
        except OSError as exc:
            self._restore()  # the counts of what is on disk, for the metadata.yaml written on close
            raise DataError(f"cannot write to {self.path}: {exc.strerror}; the data written so far is kept") from exc
        self.pending.base += len(self.pending.buf)
        self.pending.buf.clear()
        self._committed = (
            Counter(self.counts),
            [{**f, "counts": Counter(f["counts"])} for f in self.files],
            self.first_ns,
            self.last_ns,
        )

    def _restore(self) -> None:
        counts, files, self.first_ns, self.last_ns = self._committed
        self.counts, self.files = Counter(counts), [{**f, "counts": Counter(f["counts"])} for f in files]

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic in self.topics:
            return
        self.topics[topic] = msgtype
        # a topic added mid-recording (the recorder's pairs, segment by segment): the chunk in progress
        # ends first. _trailer needs an empty chunk builder: its copy of the writer shares the builder,
        # and finishing that copy would take the chunk's messages and leave the file unreadable from there on.
        self.writer._Writer__finalize_chunk()
        if self.pending.buf:
            self.files[-1]["chunks"] += 1
        self._register(topic, msgtype)
        self._commit()

    def write(self, topic: str, time_ns: int, data: bytes) -> None:
        """Write one serialised (CDR) message; ``time_ns`` is the receive time, as rosbag2 records it."""
        if self.closed:
            raise DataError(f"{self.path} is closed")
        self.writer.add_message(self.channels[topic], time_ns, bytes(data), time_ns)
        file = self.files[-1]
        for counts, key in ((self.counts, topic), (file["counts"], topic)):
            counts[key] += 1
        file["first"] = time_ns if file["first"] is None else min(file["first"], time_ns)
        file["last"] = max(file["last"], time_ns)
        self.first_ns = time_ns if self.first_ns is None else min(self.first_ns, time_ns)
        self.last_ns = max(self.last_ns, time_ns)
        if self.pending.buf:  # the writer completed a chunk: it is on disk with its trailer at once
            file["chunks"] += 1
            self._commit()
            if file["chunks"] >= self.file_chunks:
                self.split()

    def write_msg(self, topic: str, time_ns: int, msg: object) -> None:
        self.write(topic, time_ns, TYPESTORE.serialize_cdr(msg, self.topics[topic]))

    def flush(self) -> None:
        os.fsync(self.fd)

    def _finish_file(self) -> None:
        if self.fd < 0:  # a write failed while the last file was finished: what is on disk stays as it is
            return
        try:
            self.writer.finish()
            self._commit(final=True)
        finally:
            os.close(self.fd)
            self.fd = -1

    def split(self) -> None:
        """Complete the current file (summary, footer) and go on in a new one."""
        self._finish_file()
        self._open_file()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._finish_file()
        finally:
            self.sync_metadata()

    def sync_metadata(self, stage: bool = False) -> Path:
        """Write ``metadata.yaml`` (or, with ``stage``, a temporary file to rename into place later)."""
        return write_metadata(
            self.path,
            [(f["name"], f["counts"], f["first"] or 0, f["last"]) for f in self.files],
            self.topics,
            self.custom_data,
            stage,
        )


def write_metadata(
    path: Path,
    files: list[tuple[str, Counter, int, int]],
    topics: dict[str, str],
    custom_data: dict[str, str] | None = None,
    stage: bool = False,
) -> Path:
    """rosbag2's ``metadata.yaml`` (version 9), as ``ros2 bag info`` and rosbags read it.

    ``files``: ``(name, message counts by topic, first log time, last log time)`` of each MCAP file.
    """
    counts = sum((c for _, c, _, _ in files), Counter())
    used = [(n, c, a, b) for n, c, a, b in files if c.total()]
    start = min((a for _, _, a, _ in used), default=0)
    end = max((b for _, _, _, b in used), default=0)
    info = {
        "rosbag2_bagfile_information": {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [name for name, _, _, _ in files],
            "duration": {"nanoseconds": max(0, end - start)},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": counts.total(),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": [],
                        "type_description_hash": "",
                    },
                    "message_count": counts[topic],
                }
                for topic, msgtype in topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": name,
                    "starting_time": {"nanoseconds_since_epoch": first},
                    "duration": {"nanoseconds": max(0, last - first)},
                    "message_count": c.total(),
                }
                for name, c, first, last in files
            ],
            "custom_data": dict(custom_data or {}),
            "ros_distro": "jazzy",
        }
    }
    tmp = path / "metadata.yaml.tmp"
    tmp.write_text(yaml.safe_dump(info, sort_keys=False))
    return tmp if stage else tmp.replace(path / "metadata.yaml")


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


def _file_index(file: Path) -> tuple[int, str]:
    tail = file.stem.rsplit("_", 1)[-1]
    return (int(tail) if tail.isdigit() else -1, file.name)


def iter_messages(path: str | Path):
    """``(topic, msgtype, log_time, data)`` of every complete message; stops quietly at a truncated tail.

    Returns a generator; its ``truncated`` state is reported through :func:`read_raw`.
    """
    path = Path(path)
    # in split order: name_2 before name_10
    files = sorted(path.glob("*.mcap"), key=_file_index) if path.is_dir() else [path]
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


def read_raw(
    path: str | Path, joints_topic: str, pose_topic: str, joint_names: Sequence[str] | None = None
) -> RawRecording:
    """The raw streams of a recording. ``joint_names`` (the chain's): those joints are taken by name from
    every joint state that carries them all, whatever else it carries (a gripper joint, say) and in
    whatever order; a message without all of them is counted under ``joint_state_other_joints``, so a
    driver that publishes the arm in two messages loses nothing silently. Without ``joint_names``, the
    first message's joints are the recording's."""
    joint_t, q = [], []
    names = None if joint_names is None else tuple(joint_names)
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
            if len(msg.position) != len(msg.name):
                counts["joint_state_length_mismatch"] += 1
                continue
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
        wanted = "" if joint_names is None else f" (joint states with all of {', '.join(names)})"
        raise DataError(
            f"bag {path}: needs messages on {joints_topic}{wanted} and {pose_topic}; found {dict(counts) or 'none'}"
        )
    if len(frames) > 1:
        raise DataError(f"bag {path}: {pose_topic} comes in several frames {sorted(frames)}")
    jt, pt = np.array(joint_t, dtype=np.int64), np.array(pose_t, dtype=np.int64)
    jo, po = np.argsort(jt, kind="stable"), np.argsort(pt, kind="stable")
    pose_values = np.array(pose)[po]
    return RawRecording(
        jt[jo], names, np.array(q)[jo], pt[po], frames.pop(), pose_values[:, :3], pose_values[:, 3:], truncated, counts
    )


def write_pairs_into(writer: BagWriter, pairs: Pairs, log_ns: np.ndarray | None = None) -> None:
    """Append calibration pairs (the contract's two topics) to an open bag.

    ``log_ns``: the log time of each pair, e.g. the receive time of its joint state, so that pairs and raw
    topics share one time base; default: the pairs' stamps.
    """
    writer.add_topic(JOINTS_TOPIC, JOINT_STATE)
    writer.add_topic(POSE_TOPIC, POSE_STAMPED)
    positions, quats = pose_from_matrix(pairs.T)
    if pairs.position_only:
        quats = np.zeros_like(quats)  # the contract's "no orientation"
    log_ns = pairs.stamps if log_ns is None else log_ns
    for q, p, quat, ns, log in zip(pairs.q, positions, quats, pairs.stamps, log_ns, strict=True):
        ns, log = int(ns), int(log)
        writer.write_msg(JOINTS_TOPIC, log, joint_state_msg(ns, pairs.joint_names, q))
        writer.write_msg(POSE_TOPIC, log, pose_stamped_msg(ns, pairs.frame_id, p, quat))
    writer.sync_metadata()
