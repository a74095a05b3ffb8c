"""The recorder: raw joint states and tracker poses into an MCAP bag, plus the aligned calibration pairs.

Messages arrive serialised (``raw=True``) and go straight into the bag; their stamps and values also go
into in-memory buffers. When a recording stops (``~/stop``, SIGINT or SIGTERM) the buffers are aligned
by the same code as ``hybrid-kinematics align`` and the pairs are appended to the bag before it is
closed. A killed recorder leaves a bag whose complete chunks read back, and which ``align`` turns into
pairs. Diagnostics (rates, counts, rejections, the clock offset) are published once a second; they
WARN on lost messages, an unstable clock offset or frequent beam breaks, and are an ERROR once the bag
cannot be written. Subscriptions are reliable unless a publisher is best-effort (``reliability: auto``).
Subscriptions run on the EventsExecutor: the only executor here that keeps up with 3 kHz at low CPU.
"""

from __future__ import annotations

import os

# One BLAS thread, set before numpy loads OpenBLAS: the clock estimate's matrix work with two threads on a
# busy 2-core machine spun for 3.1 s per SVD instead of 0.09 s, and starved the 3 kHz subscription.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib
import signal
import sys
import threading
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from hybrid_kinematics_ros.calibration.alignment import AlignOptions, align
from hybrid_kinematics_ros.calibration.clock import estimate_offset
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.columns import Columns
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
        self.lost: Counter = Counter()  # what the middleware reports as lost before it reached us
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
        if autostart:
            try:
                self.start(self.bag_name or None)
            except DataError as exc:  # an existing bag or an unwritable folder
                raise StartupError(str(exc)) from exc

    # ------------------------------------------------------------------ subscriptions
    def _subscribe(self, topic: str, msgtype, callback, reliability: ReliabilityPolicy) -> None:
        events = SubscriptionEventCallbacks(message_lost=lambda info, t=topic: self._on_lost(t, info))
        qos = QoSProfile(depth=10000, reliability=reliability)
        sub = self.create_subscription(msgtype, topic, callback, qos, raw=True, event_callbacks=events)
        self.subscriptions_[topic] = (sub, reliability, msgtype, callback)

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
        self.joints = Columns(self.chain.dof)
        self.joint_rx = Columns(0)  # receive times (ns) of the joint states, the log time of their pairs
        self.poses = Columns(7)
        self.names: list[str] | None = None
        self.frame = ""
        self.received = Counter()
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
        try:
            writer.split()  # the raw file: complete on disk
            self.get_logger().info(f"raw recording finalised ({dict(writer.counts)}); aligning")
            rec = self._recording()
            result = align(self.chain, rec, self.options, self.pairs_frame or None)
            writer.custom_data.update(
                {
                    "clock_offset_s": repr(result.offset_s),
                    "clock_skew_ppm": repr(result.skew_ppm),
                    "pairs": str(len(result.pairs)),
                    **{f"rejected_{k}": str(v) for k, v in result.rejected.items()},
                }
            )
            write_pairs_into(writer, result.pairs, self._receive_times(result.pairs.stamps))
            self.last_offset, self.last_rejected, self.last_pairs = result.offset_s, result.rejected, len(result.pairs)
            message += (
                f" with {len(result.pairs)} pairs; clock offset {result.offset_s * 1e3:.3f} ms, "
                f"skew {result.skew_ppm:.2f} ppm; rejected {dict(result.rejected)}"
            )
        except (CalibrationError, DataError, ValueError) as exc:
            message += f" without pairs ({exc}); align it later with hybrid-kinematics align"
        finally:
            with contextlib.suppress(DataError):  # a write failure is reported already
                writer.close()
        self.get_logger().info(message)
        return message

    def _receive_times(self, stamps: np.ndarray) -> np.ndarray:
        """Log times of pairs: the receive time of the joint state each comes from, so that pairs and raw
        topics share one time base in the bag (``starting_time``, ``duration``, playback order)."""
        jt, rx = self.joints.view()[0], self.joint_rx.view()[0]
        order = np.argsort(jt, kind="stable")
        jt, rx = jt[order], rx[order]
        index = np.clip(np.searchsorted(jt, stamps), 0, len(jt) - 1)
        return np.where(jt[index] == stamps, rx[index], stamps)

    def _recording(self, last_s: float | None = None) -> RawRecording:
        """Everything recorded so far, or about the last ``last_s`` seconds of it (a copy either way)."""
        if last_s is None:
            (jt, q), (pt, p) = self.joints.view(), self.poses.view()
        else:
            elapsed = max(time.monotonic() - self.started, 1e-3)
            (jt, q), (pt, p) = (c.view(int(1.5 * last_s * c.n / elapsed) + 2) for c in (self.joints, self.poses))
        if not len(jt) or not len(pt):
            raise DataError(f"nothing to align: {len(jt)} joint states and {len(pt)} tracker poses")
        jo, po = np.argsort(jt, kind="stable"), np.argsort(pt, kind="stable")
        return RawRecording(
            jt[jo],
            tuple(self.names or self.chain.joint_names),
            q[jo],
            pt[po],
            self.frame,
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

    def _on_joints(self, raw: bytes) -> None:
        now = time.time_ns()
        if not self._write(self.joints_topic, now, raw):
            return
        msg = deserialize_message(raw, JointState)
        self.received["joint_states"] += 1
        index = {n: i for i, n in enumerate(msg.name)}
        if len(msg.name) != len(msg.position) or any(n not in index for n in self.chain.joint_names):
            self.received["joint_states_without_robot_joints"] += 1
            return
        self.names = list(self.chain.joint_names)
        self.joints.append(
            msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
            [msg.position[index[n]] for n in self.chain.joint_names],
        )
        self.joint_rx.append(now, ())

    def _on_pose(self, raw: bytes) -> None:
        if not self._write(self.pose_topic, time.time_ns(), raw):
            return
        self.received["tracker_poses"] += 1
        try:
            stamp, self.frame, values = decode_pose_stamped(raw)
        except DataError:  # a big-endian publisher: the slow, general path
            msg = deserialize_message(raw, PoseStamped)
            p, o = msg.pose.position, msg.pose.orientation
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            self.frame, values = msg.header.frame_id, (p.x, p.y, p.z, o.x, o.y, o.z, o.w)
        self.poses.append(stamp, values)
        if self.last_pose_stamp is not None and stamp - self.last_pose_stamp > self.options.max_gap_s * 1e9:
            self.beam_breaks += 1  # a gap alignment will not bridge
        self.last_pose_stamp = stamp

    def _on_lost(self, topic: str, info) -> None:
        self.lost[topic] = info.total_count

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
        if time.monotonic() - self.started < 20.0 or self.poses.n < 5000:
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
            values.update({f"lost_{t}": str(n) for t, n in self.lost.items()})
            problems = self._problems(elapsed)
            self._start_offset_estimate()
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
        lost = sum(self.lost.values())
        if lost:
            out.append((DiagnosticStatus.WARN, f"{lost} messages lost before they reached the recorder"))
        per_min = 60.0 * self.beam_breaks / max(elapsed, 1.0)
        if self.beam_breaks >= 3 and per_min > self.max_beam_breaks:
            out.append((DiagnosticStatus.WARN, f"beam breaks {per_min:.1f}/min (more than {self.max_beam_breaks:g})"))
        if len(self.offsets) >= 2 and abs(self.offsets[-1] - self.offsets[-2]) > self.offset_warn_s:
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
