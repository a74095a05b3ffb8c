"""The recorder: raw joint states and tracker poses into an MCAP bag, plus the aligned calibration pairs.

Messages arrive serialised (``raw=True``) and go straight into the bag; their stamps and values also go
to a :class:`StreamingAligner`, which keeps only the last couple of minutes: a worker thread aligns the
recording segment by segment as it goes (``align_segment_s``), and the executor thread writes each
segment's pairs into the bag, so memory stays bounded for sessions of hours. When a recording stops
(``~/stop``, SIGINT or SIGTERM) the rest is aligned and its pairs are appended before the bag is closed;
a recording shorter than a segment and its context is aligned exactly as ``hybrid-kinematics align``
does it. A killed recorder leaves a bag whose complete chunks read back, and which ``align`` turns into
pairs. Diagnostics (rates, counts, rejections, the clock offset) are published once a second; they
WARN on missing joint states, an unstable clock offset or frequent beam breaks, and are an ERROR once the bag
cannot be written. Subscriptions are reliable unless a publisher is best-effort (``reliability: auto``).
Subscriptions run on the EventsExecutor: the only executor here that keeps up with 3 kHz at low CPU.
"""

from __future__ import annotations

import os

# One BLAS thread, set before numpy loads OpenBLAS: the clock estimate's matrix work with two threads on a
# busy 2-core machine spins for many times an SVD's own time, and starves the 3 kHz subscription.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib
import signal
import sys
import threading
import time
from collections import Counter, deque
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from hybrid_kinematics_ros.calibration.alignment import AlignOptions
from hybrid_kinematics_ros.calibration.clock import estimate_offset
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.windowed import (
    CONTEXT_S,
    SEGMENT_S,
    SegmentPairs,
    StreamingAligner,
    fit_clock,
)
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.pairs import JOINT_STATE, POSE_STAMPED
from hybrid_kinematics_ros.io.raw_bag import BagWriter, RawRecording, decode_pose_stamped, write_pairs_into
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.nodes.runtime import StartupError, read_only_parameter, run_node

RELIABILITY = {"auto": None, "reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}


class RecorderNode(Node):
    def __init__(self, name: str = "recorder_node", **kwargs) -> None:
        super().__init__(name, **kwargs)

        def declare(name: str, default, description: str):
            return read_only_parameter(self, name, default, description)

        self.joints_topic = declare("joint_states_topic", "/joint_states", "raw joint states")
        self.pose_topic = declare("tracker_topic", "/tracker/pose", "raw tracker poses (geometry_msgs/PoseStamped)")
        self.output_dir = Path(declare("output_dir", "bags", "folder of the recordings"))
        self.bag_name = declare("bag_name", "", "name of the first bag (default: recording_<UTC time>)")
        robot = declare("robot", "ur10", "robot config YAML or embedded robot, for alignment")
        self.pairs_frame = declare("pairs_frame_id", "", "frame_id of the pairs (default: the tracker's frame)")
        offset = declare("clock_offset_s", float("nan"), "tracker minus robot clock (s); NaN: estimate it")
        self.options = AlignOptions(
            max_gap_s=declare("max_gap_s", 0.02, "longest tracker gap bridged by interpolation (s)"),
            max_joint_speed=declare("max_joint_speed", 1.0, "reject samples while any joint moves faster (rad/s)"),
            offset_s=None if np.isnan(offset) else offset,
            still_min_s=declare("static_min_s", 0.0, "> 0: static mode, one averaged pair per still window"),
        )
        self.segment_s = declare("align_segment_s", SEGMENT_S, "align while recording, this much at a time (s)")
        self.context_s = declare("align_context_s", CONTEXT_S, "data either side of a segment for its clock (s)")
        autostart = declare("autostart", True, "start recording at once")
        try:
            self.chain = load_robot_config(robot).chain
        except KinematicsError as exc:
            raise StartupError(f"parameter robot: {exc}") from exc
        reliability = declare(
            "reliability", "auto", "auto (reliable unless a publisher is best-effort), reliable or best_effort"
        )
        if reliability not in RELIABILITY:
            raise StartupError(f"parameter reliability: {reliability!r} is not one of {sorted(RELIABILITY)}")
        self.reliability = reliability
        self.max_beam_breaks = declare("max_beam_breaks_per_min", 6.0, "more tracker gaps a minute: WARN")
        self.offset_warn_s = declare("offset_warn_s", 1e-3, "running clock estimates further apart: WARN")
        self.no_joints_warn_s = declare(
            "no_joints_warn_s", 3.0, "recording this long without a joint state that has the robot's joints: WARN"
        )
        self.subscriptions_: dict[str, tuple] = {}  # topic -> (subscription, reliability, type, callback)
        for msgtype, topic, callback in (
            (JointState, self.joints_topic, self._on_joints),
            (PoseStamped, self.pose_topic, self._on_pose),
        ):
            self._subscribe(topic, msgtype, callback, RELIABILITY[reliability if reliability != "auto" else "reliable"])
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/stop", self._on_stop)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._diagnostics)
        self.writer: BagWriter | None = None
        self.last_offset: float | None = None
        self.offsets: list[float] = []  # running estimates of this recording
        self.write_error = ""
        self.last_rejected: Counter = Counter()
        self.last_pairs = 0
        self._offset_worker: threading.Thread | None = None
        self._next_offset = 0.0
        self._align_worker: threading.Thread | None = None
        self._aligned: deque[SegmentPairs] = deque()  # aligned by the worker, for the executor thread to write
        self._align_error = ""
        if autostart:
            try:
                self.start(self.bag_name or None)
            except DataError as exc:  # an existing bag or an unwritable folder
                raise StartupError(str(exc)) from exc

    # ------------------------------------------------------------------ subscriptions
    def _subscribe(self, topic: str, msgtype, callback, reliability: ReliabilityPolicy) -> None:
        # No message-lost event handler: in Jazzy's rmw_fastrtps, taking that event while a DDS receive thread
        # reports a lost sample deadlocks the two (AB-BA on the reader's and the event's mutexes, an rmw_fastrtps
        # bug): a saturated machine would hang the recorder for good. The stream's own gaps show what is missing.
        qos = QoSProfile(depth=10000, reliability=reliability)
        sub = self.create_subscription(msgtype, topic, callback, qos, raw=True)
        self.subscriptions_[topic] = (sub, reliability, msgtype, callback)

    def _no_joints_message(self, elapsed: float) -> str:
        """Why no pair can come of this recording yet, logged as a warning once per cause (nothing at all,
        then the names that came instead): the whole session would otherwise end with zero pairs (a driver
        naming its joints otherwise, say)."""
        without = self.received["joint_states_without_robot_joints"]
        text = f"no joint state with the robot's joints ({', '.join(self.chain.joint_names)}) in {elapsed:.0f} s"
        if without:
            text += f": {without} on {self.joints_topic} carried {', '.join(self.other_joint_names)} instead"
        else:
            text += f": nothing on {self.joints_topic}"
        if self._warned_no_joints != self.other_joint_names:
            self._warned_no_joints = self.other_joint_names
            self.get_logger().warning(text)
        return text

    def _adapt_qos(self) -> None:
        """``reliability: auto``: best-effort as soon as a publisher is best-effort (a reliable subscription
        never matches one), reliable again when all are reliable, as rosbag2's adaptive QoS does."""
        if self.reliability != "auto":
            return
        for topic, (sub, current, msgtype, callback) in list(self.subscriptions_.items()):
            offered = [i.qos_profile.reliability for i in self.get_publishers_info_by_topic(topic)]
            if not offered:
                continue
            wanted = (
                ReliabilityPolicy.BEST_EFFORT
                if ReliabilityPolicy.BEST_EFFORT in offered
                else ReliabilityPolicy.RELIABLE
            )
            if wanted != current:
                self.destroy_subscription(sub)
                self._subscribe(topic, msgtype, callback, wanted)
                self.get_logger().info(f"{topic}: subscribed {wanted.name.lower()}, as its publishers offer")

    # ------------------------------------------------------------------ recording
    def start(self, name: str | None = None) -> Path:
        if self.writer is not None:
            raise DataError(f"already recording into {self.writer.path}")
        name = name or "recording_" + datetime.now(UTC).strftime("%Y%m%d_%H%M%S_%f")
        try:
            self.output_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"parameter output_dir: cannot create {self.output_dir}: {exc.strerror}") from exc
        writer = BagWriter(self.output_dir / name)
        writer.add_topic(self.joints_topic, JOINT_STATE)
        writer.add_topic(self.pose_topic, POSE_STAMPED)
        self.aligner = StreamingAligner(
            self.chain, self.options, self.pairs_frame or None, segment_s=self.segment_s, context_s=self.context_s
        )
        self._aligned, self._align_error = deque(), ""
        self.received = Counter()
        self.other_joint_names: tuple[str, ...] = ()  # of the last joint state without the robot's joints
        self._warned_no_joints: tuple[str, ...] | None = None  # the cause last logged (the names seen instead)
        self.beam_breaks = 0
        self.last_pose_stamp: int | None = None
        self.offsets = []
        self.write_error = ""
        self.started = time.monotonic()
        self.writer = writer
        self.get_logger().info(f"recording into {writer.path}")
        return writer.path

    def stop(self) -> str:
        """Close the raw data, then align it and add the pairs; the raw data is kept whatever happens.

        The raw file is completed before the alignment starts: a SIGTERM's grace period (or a SIGKILL
        after it) during a long alignment costs the pairs at most, never recorded data.
        """
        writer, self.writer = self.writer, None
        if writer is None:
            raise DataError("not recording")
        message = f"closed {writer.path}"
        aligner = self.aligner
        try:
            writer.split()  # the raw file: complete on disk
            self.get_logger().info(f"raw recording finalised ({dict(writer.counts)}); aligning")
            if self._align_worker is not None:
                self._align_worker.join()  # a segment in progress
            self._write_aligned(writer)
            if aligner.joints.n == 0 or aligner.poses.n == 0:
                raise DataError(
                    f"nothing to align: {aligner.joints.n} joint states and {aligner.poses.n} tracker poses"
                )
            self._aligned.extend(aligner.poll(final=True))
            self._write_aligned(writer)
            clock = aligner.summary_clock()
            offset = float("nan") if clock is None else clock.offset_s
            skew = 0.0 if clock is None else clock.skew_ppm
            writer.custom_data.update(
                {
                    "clock_offset_s": repr(offset),
                    "clock_skew_ppm": repr(skew),
                    "pairs": str(aligner.pairs),
                    **{f"rejected_{k}": str(v) for k, v in (+aligner.rejected).items()},
                }
            )
            writer.sync_metadata()
            self.last_offset, self.last_rejected, self.last_pairs = offset, +aligner.rejected, aligner.pairs
            message += (
                f" with {aligner.pairs} pairs; clock offset {offset * 1e3:.3f} ms, "
                f"skew {skew:.2f} ppm; rejected {dict(+aligner.rejected)}"
            )
        except (CalibrationError, DataError, ValueError) as exc:
            done = f"{aligner.pairs} pairs of the earlier segments in the bag; " if aligner.pairs else ""
            message += f" without pairs ({exc}); {done}align it later with hybrid-kinematics align"
        finally:
            with contextlib.suppress(DataError):  # a write failure is reported already
                writer.close()
        self.get_logger().info(message)
        return message

    def _write_aligned(self, writer: BagWriter | None = None) -> None:
        """Write the pairs of the segments aligned so far (executor thread: the bag writer is not shared)."""
        writer = writer or self.writer
        while self._aligned:
            segment = self._aligned.popleft()
            if writer is None or self.write_error or not len(segment.result.pairs):
                continue
            try:
                write_pairs_into(writer, segment.result.pairs, segment.log_ns)
            except DataError as exc:
                self.write_error = str(exc)
                self.get_logger().error(f"{exc}; not recording any more")

    def _start_segment_alignment(self) -> None:
        """Align the segments whose data is complete, in a worker thread (a segment takes seconds)."""
        self._write_aligned()
        if self._align_worker is not None and self._align_worker.is_alive():
            return
        aligner = self.aligner

        def work() -> None:
            try:
                self._aligned.extend(aligner.poll())
            except (CalibrationError, DataError, ValueError) as exc:  # the raw data is safe; say so once
                if not self._align_error:
                    self.get_logger().warning(f"aligning while recording failed ({exc}); it is retried on stop")
                self._align_error = str(exc)

        self._align_worker = threading.Thread(target=work, name="align_segments", daemon=True)
        self._align_worker.start()

    def _recording(self, last_s: float) -> RawRecording:
        """About the last ``last_s`` seconds (a copy)."""
        elapsed = max(time.monotonic() - self.started, 1e-3)
        (jt, q), (pt, p) = self.aligner.recent(
            int(1.5 * last_s * self.aligner.joints.n / elapsed) + 2,
            int(1.5 * last_s * self.aligner.poses.n / elapsed) + 2,
        )
        if not len(jt) or not len(pt):
            raise DataError(f"nothing to align: {len(jt)} joint states and {len(pt)} tracker poses")
        jo, po = np.argsort(jt, kind="stable"), np.argsort(pt, kind="stable")
        return RawRecording(
            jt[jo],
            self.chain.joint_names,
            q[jo, :-1],
            pt[po],
            self.aligner.frame,
            p[po, :3],
            p[po, 3:],
            False,
            Counter(self.received),
        )

    # ------------------------------------------------------------------ callbacks
    def _write(self, topic: str, time_ns: int, raw: bytes) -> bool:
        """Into the bag; a failure (disk full, file size limit) stops the recording's writes and is an ERROR."""
        if self.writer is None or self.write_error:
            return False
        try:
            self.writer.write(topic, time_ns, raw)
        except DataError as exc:
            self.write_error = str(exc)
            self.get_logger().error(f"{exc}; not recording any more")
            return False
        return True

    def _now_ns(self) -> int:
        """The bag's log time: the node's clock, so a recording under ``use_sim_time`` is on the sim clock."""
        return self.get_clock().now().nanoseconds

    def _on_joints(self, raw: bytes) -> None:
        now = self._now_ns()
        if not self._write(self.joints_topic, now, raw):
            return
        msg = deserialize_message(raw, JointState)
        self.received["joint_states"] += 1
        index = {n: i for i, n in enumerate(msg.name)}
        if len(msg.name) != len(msg.position) or any(n not in index for n in self.chain.joint_names):
            self.received["joint_states_without_robot_joints"] += 1
            self.other_joint_names = tuple(msg.name)
            return
        self.aligner.add_joints(
            msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
            [msg.position[index[n]] for n in self.chain.joint_names],
            now,
        )

    def _on_pose(self, raw: bytes) -> None:
        if not self._write(self.pose_topic, self._now_ns(), raw):
            return
        self.received["tracker_poses"] += 1
        try:
            stamp, frame, values = decode_pose_stamped(raw)
        except DataError:  # a big-endian publisher: the slow, general path
            msg = deserialize_message(raw, PoseStamped)
            p, o = msg.pose.position, msg.pose.orientation
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            frame, values = msg.header.frame_id, (p.x, p.y, p.z, o.x, o.y, o.z, o.w)
        self.aligner.add_pose(stamp, values, frame)
        if self.last_pose_stamp is not None and stamp - self.last_pose_stamp > self.options.max_gap_s * 1e9:
            self.beam_breaks += 1  # a gap alignment will not bridge
        self.last_pose_stamp = stamp

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.message = f"recording into {self.start()}"
            response.success = True
        except DataError as exc:
            response.success, response.message = False, str(exc)
        return response

    def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.message = self.stop()
            response.success = True
        except DataError as exc:
            response.success, response.message = False, str(exc)
        return response

    def _start_offset_estimate(self) -> None:
        """Every 10 s, estimate the clock offset over the last 30 s in a worker thread.

        Shorter windows of slow motion give estimates milliseconds off. The estimate takes about a
        second; on the executor thread it would stall the 3 kHz stream for that long, and the
        publisher's queue would overflow.
        """
        busy = self._offset_worker is not None and self._offset_worker.is_alive()
        if self.options.offset_s is not None or busy or time.monotonic() < self._next_offset:
            return
        if time.monotonic() - self.started < 20.0 or self.aligner.poses.n < 5000:
            return
        if self.aligner.estimates:  # the segments' estimates (one a segment) take over from here
            return
        self._next_offset = time.monotonic() + 10.0
        recent = self._recording(last_s=30.0)

        def estimate() -> None:
            with contextlib.suppress(CalibrationError, DataError, ValueError):  # too little motion: keep the last
                self.last_offset = estimate_offset(self.chain, recent, self.options.max_offset_s)
                self.offsets.append(self.last_offset)

        self._offset_worker = threading.Thread(target=estimate, name="offset_estimate", daemon=True)
        self._offset_worker.start()

    def _diagnostics(self) -> None:
        self._adapt_qos()
        status = DiagnosticStatus(name=self.get_name(), hardware_id="laser_tracker")
        values = {"recording": str(self.writer is not None)}
        problems: list[tuple[bytes, str]] = []
        if self.writer is not None:
            elapsed = max(time.monotonic() - self.started, 1e-9)
            values.update(
                {
                    "bag": str(self.writer.path),
                    "joint_states": str(self.received["joint_states"]),
                    "tracker_poses": str(self.received["tracker_poses"]),
                    "joint_rate_hz": f"{self.received['joint_states'] / elapsed:.1f}",
                    "tracker_rate_hz": f"{self.received['tracker_poses'] / elapsed:.1f}",
                    "beam_breaks": str(self.beam_breaks),
                }
            )
            problems = self._problems(elapsed)
            self._start_offset_estimate()
            self._start_segment_alignment()
            values["retained_samples"] = str(self.aligner.retained)
            values["pairs_so_far"] = str(self.aligner.pairs)
            estimates = self.aligner.estimates
            if estimates:
                self.last_offset = estimates[-1].offset_s
        if self.last_offset is not None:
            values["clock_offset_ms"] = f"{self.last_offset * 1e3:.3f}"
        values.update({f"rejected_{k}": str(v) for k, v in self.last_rejected.items()})
        if self.last_pairs:
            values["pairs_last_recording"] = str(self.last_pairs)
        status.level = max((level for level, _ in problems), default=DiagnosticStatus.OK)
        status.message = "recording" if self.writer is not None else "idle"
        if problems:
            status.message += ": " + "; ".join(text for _, text in problems)
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def _problems(self, elapsed: float) -> list[tuple[bytes, str]]:
        """What makes this recording WARN (data lost or doubtful) or ERROR (nothing written any more)."""
        out = []
        if self.write_error:
            out.append((DiagnosticStatus.ERROR, f"write failed: {self.write_error}"))
        if self.aligner.joints.n == 0 and elapsed >= self.no_joints_warn_s:
            out.append((DiagnosticStatus.WARN, self._no_joints_message(elapsed)))
        per_min = 60.0 * self.beam_breaks / max(elapsed, 1.0)
        if self.beam_breaks >= 3 and per_min > self.max_beam_breaks:
            out.append((DiagnosticStatus.WARN, f"beam breaks {per_min:.1f}/min (more than {self.max_beam_breaks:g})"))
        estimates = self.aligner.estimates if self.writer is not None else []
        if len(estimates) >= 2:  # the segments': the newest against the trend (offset and skew) of the others
            trend = fit_clock(estimates[:-1], estimates[0].stamp_ns)
            off = abs(estimates[-1].offset_s - float(trend.offset_at(np.array([estimates[-1].stamp_ns]))[0]))
            if off > self.offset_warn_s:
                out.append(
                    (
                        DiagnosticStatus.WARN,
                        f"clock offset unstable: the last segment's is {1e3 * off:.2f} ms off the trend",
                    )
                )
        elif len(self.offsets) >= 2 and abs(self.offsets[-1] - self.offsets[-2]) > self.offset_warn_s:
            jump = 1e3 * abs(self.offsets[-1] - self.offsets[-2])
            out.append((DiagnosticStatus.WARN, f"clock offset unstable: the last estimates differ by {jump:.2f} ms"))
        return out


def main(args: list[str] | None = None) -> int:
    """SIGINT and SIGTERM end the spin loop, so the bag is finalised with its pairs."""
    from rclpy.experimental import EventsExecutor

    stopping: list[bool] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.append(True))

    def spin(executor) -> None:
        # EventsExecutor.spin() ignores SIGINT here; this loop does not
        while rclpy.ok() and not stopping:
            executor.spin_once(timeout_sec=0.1)

    def finish(node: RecorderNode) -> None:
        if node.writer is not None:
            node.stop()

    return run_node(
        "recorder_node",
        RecorderNode,
        EventsExecutor,
        args,
        spin=spin,
        on_exit=finish,
        signal_handler_options=rclpy.signals.SignalHandlerOptions.NO,
    )


if __name__ == "__main__":
    sys.exit(main())
