"""The simulated cell: the virtual robot's joints at 110 Hz and laser-tracker poses at 3 kHz.

Samples are computed in vectorised blocks of 10 ms and published from a loop that sleeps until each
sample is due (a ROS timer falls short of 3 kHz here; busy-waiting holds the time slightly closer but
takes a whole core from the recorder on a 2-core machine). Stamps are the scheduled times, so
lateness moves delivery, never the data. Computing a block makes the samples right after it up to about
1 ms late; a producer thread does not help, because the computation holds the GIL. The tracker has its
own clock (offset and drift against the robot's), noise, and beam breaks during which nothing is
published. It may stand in its own frame, see a plain reflector (zero quaternions), and the joint
readings may carry encoder noise and quantisation.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState

from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig, load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix
from hybrid_kinematics_ros.nodes.runtime import StartupError, read_only_parameter, run_node
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.trajectory import JointStep, random_waypoints, through

BLOCK_S = 0.01
LATENESS_SAMPLES = 2_000_000


def _tracker_frames(declare: Callable[..., Any]) -> dict[str, dict[str, list[float]]]:
    """The tracker's placement and the target's mount from the node's parameters (zero: the config's)."""
    return {
        "base_to_tracker": {
            "xyz": declare("base_to_tracker_xyz", [0.0, 0.0, 0.0], "tracker frame in the robot base (m)"),
            "rpy": declare("base_to_tracker_rpy", [0.0, 0.0, 0.0], "its roll, pitch, yaw (rad)"),
        },
        "flange_to_target": {
            "xyz": declare("flange_to_target_xyz", [0.0, 0.0, 0.0], "tracker target on the flange (m)"),
            "rpy": declare("flange_to_target_rpy", [0.0, 0.0, 0.0], "its roll, pitch, yaw (rad)"),
        },
    }


def _slip(value: list[float], dof: int) -> JointStep | None:
    """The ``slip`` parameter ``[joint index, rad, after s]`` as a joint step (None at 0 rad)."""
    if len(value) != 3 or not float(value[0]).is_integer():
        raise StartupError(f"parameter slip: {list(value)} is not [joint index, rad, after s]")
    slip = JointStep(int(value[0]), float(value[1]), float(value[2])) if value[1] else None
    if slip is not None and not (0 <= slip.joint < dof and np.isfinite(slip.rad) and slip.after_s >= 0):
        raise StartupError(f"parameter slip: {list(value)}: give a joint index below {dof}, rad, s >= 0")
    return slip


def _waypoints(cfg: RobotConfig, pattern: str, count: int, rng: np.random.Generator) -> np.ndarray:
    """The waypoints of the ``pattern``: ``count`` random ones, or the corners of a cube about a centre pose."""
    if pattern != "cube":
        return random_waypoints(cfg.chain, count, rng)
    centre = 0.5 * (cfg.chain.lower + cfg.chain.upper)
    if cfg.name == "ur10":
        centre = np.clip(np.array([0.0, -1.2, 1.4, -1.8, -1.5, 0.0])[: cfg.chain.dof], cfg.chain.lower, cfg.chain.upper)
    from hybrid_kinematics_ros.ik.cube import cube_waypoints  # IK loads torch: only for this pattern
    from hybrid_kinematics_ros.ik.errors import IKError

    try:
        return cube_waypoints(cfg.chain, centre)
    except IKError as exc:
        raise StartupError(f"parameter pattern cube: {exc}") from exc


class SimCellNode(Node):
    def __init__(self, name: str = "sim_cell_node", **kwargs) -> None:
        super().__init__(name, **kwargs)

        def declare(name: str, default, description: str):
            return read_only_parameter(self, name, default, description)

        robot = declare("robot", "ur10", "robot config YAML or embedded robot name")
        pattern = declare("pattern", "random", "waypoint pattern: random or cube")
        waypoints = declare("waypoints", 40, "number of random waypoints")
        speed = declare("speed", 0.25, "mean speed of the fastest joint between waypoints (rad/s)")
        dwell = declare("dwell_s", 0.3, "still time at each waypoint (s)")
        self.joint_rate = declare("joint_rate_hz", 110.0, "joint-state rate")
        self.tracker_rate = declare("tracker_rate_hz", 3000.0, "tracker rate")
        self.offset_s = declare("tracker_clock_offset_s", 0.0123, "tracker clock minus robot clock (s)")
        self.drift = declare("tracker_clock_drift_ppm", 0.0, "tracker clock drift (ppm)") * 1e-6
        self.dropout_rate = declare("dropout_rate_hz", 0.05, "beam breaks per second")
        self.dropout_s = declare("dropout_duration_s", 0.2, "length of a beam break (s)")
        noise = declare("noise", True, "tracker noise on")
        seed = declare("seed", 1, "seed of waypoints, noise and beam breaks")
        self.tracker_frame = declare("tracker_frame", "tracker", "frame_id of the tracker poses")
        self.wait_s = declare(
            "wait_for_subscribers_s", 10.0, "wait up to this long for a subscriber on both topics before publishing"
        )

        frames = _tracker_frames(declare)
        self.plain_reflector = declare(
            "plain_reflector", False, "the target gives no orientation: publish zero quaternions"
        )
        self.encoder_noise = declare("encoder_noise_rad", 0.0, "joint encoder noise, standard deviation (rad)")
        self.encoder_step = declare("encoder_resolution_rad", 0.0, "joint encoder quantisation step (rad); 0: none")
        slip = declare(
            "slip", [0.0, 0.0, 0.0], "joint index, rad, after s: that joint slips then, its encoder does not see it"
        )
        cfg = load_robot_config(robot)
        self.slip = _slip(slip, cfg.chain.dof)
        self.cell = VirtualCell.from_config(cfg, noise=noise)
        if any(np.any(np.asarray(v, dtype=float) != 0.0) for f in frames.values() for v in f.values()):
            tracker = Tracker.from_config({**cfg.tracker, **frames}, noise=noise)
            self.cell = VirtualCell(cfg, self.cell.robot, tracker)
        self.names = list(cfg.chain.joint_names)
        self.rng = np.random.default_rng(seed)
        points = _waypoints(cfg, pattern, int(waypoints), self.rng)
        self.trajectory = through(points, speed, dwell)
        qos = QoSProfile(depth=1000)
        self.joint_pub = self.create_publisher(JointState, "/joint_states", qos)
        self.pose_pub = self.create_publisher(PoseStamped, "/tracker/pose", qos)
        self.stats = {"joint_states": 0, "tracker_poses": 0, "dropped_by_beam_break": 0}
        self.late_us = np.zeros(LATENESS_SAMPLES, dtype=np.float32)  # a ring: the last 10 min at 3.1 kHz
        self.events = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        self.create_timer(10.0, self._report)
        self.get_logger().info(
            f"simulating {cfg.name}: {pattern} trajectory of {len(points)} waypoints, "
            f"period {self.trajectory.period:.1f} s, joints {self.joint_rate:g} Hz, "
            f"tracker {self.tracker_rate:g} Hz, clock offset {self.offset_s * 1e3:g} ms"
        )

    def _beam_breaks(self, t0: float, t1: float) -> list[tuple[float, float]]:
        count = self.rng.poisson(self.dropout_rate * (t1 - t0))
        starts = self.rng.uniform(t0, t1, count)
        return [(s, s + self.dropout_s) for s in starts]

    def _block(self, t0: float, rate: float, phase: int) -> tuple[np.ndarray, int]:
        k = np.arange(phase, phase + int(np.ceil(BLOCK_S * rate)) + 1)
        t = k / rate
        return t[(t >= t0) & (t < t0 + BLOCK_S)], int(k[-1])

    def _run(self) -> None:
        try:
            self._publish_loop()
        except Exception:  # rclpy raises RCLError once SIGINT has shut the context down mid-publish
            if rclpy.ok() and not self._stop.is_set():
                raise

    def _publish_loop(self) -> None:
        # Messages published before discovery has matched a subscriber are lost to it: wait for one.
        give_up = time.perf_counter() + self.wait_s
        while time.perf_counter() < give_up and not self._stop.is_set():
            if self.joint_pub.get_subscription_count() and self.pose_pub.get_subscription_count():
                time.sleep(0.5)  # the other endpoints of the subscriber's participant match moments later
                break
            time.sleep(0.05)
        start_ns = self.get_clock().now().nanoseconds
        start = time.perf_counter()
        jk = tk = 0
        breaks: list[tuple[float, float]] = []
        t0 = 0.0
        while not self._stop.is_set() and rclpy.ok():
            tj, _ = self._block(t0, self.joint_rate, jk)
            tt, _ = self._block(t0, self.tracker_rate, tk)
            jk += len(tj)
            tk += len(tt)
            breaks = [b for b in breaks if b[1] > t0] + self._beam_breaks(t0, t0 + BLOCK_S)
            qj = self._encoders(self.trajectory(tj))
            reached = self.trajectory(tt)
            measured = self.cell.measure(reached if self.slip is None else self.slip.reached(reached, tt), self.rng)
            positions, quats = pose_from_matrix(measured)
            if self.plain_reflector:
                quats = np.zeros_like(quats)  # the contract's "no orientation"
            events = [(t, 0, i) for i, t in enumerate(tj)] + [(t, 1, i) for i, t in enumerate(tt)]
            events.sort()
            for t, kind, i in events:
                delay = start + t - time.perf_counter()
                if delay > 0.0:
                    time.sleep(delay)
                late = time.perf_counter() - (start + t)
                robot_ns = start_ns + round(t * 1e9)
                if kind == 0:
                    self._publish_joints(robot_ns, qj[i])
                elif any(b0 <= t < b1 for b0, b1 in breaks):
                    self.stats["dropped_by_beam_break"] += 1
                else:
                    tracker_ns = robot_ns + round((self.offset_s + self.drift * t) * 1e9)
                    self._publish_pose(tracker_ns, positions[i], quats[i])
                self.late_us[self.events % LATENESS_SAMPLES] = late * 1e6
                self.events += 1
                if self._stop.is_set():
                    return
            t0 += BLOCK_S

    def _encoders(self, q: np.ndarray) -> np.ndarray:
        """Joint readings: the true joints with encoder noise, quantised to the encoder's resolution."""
        if self.encoder_noise > 0.0:
            q = q + self.rng.normal(0.0, self.encoder_noise, q.shape)
        if self.encoder_step > 0.0:
            q = np.round(q / self.encoder_step) * self.encoder_step
        return q

    def _publish_joints(self, ns: int, q: np.ndarray) -> None:
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msg.name = self.names
        msg.position = q.tolist()
        self.joint_pub.publish(msg)
        self.stats["joint_states"] += 1

    def _publish_pose(self, ns: int, p: np.ndarray, quat: np.ndarray) -> None:
        msg = PoseStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msg.header.frame_id = self.tracker_frame
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = p.tolist()
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = quat.tolist()
        self.pose_pub.publish(msg)
        self.stats["tracker_poses"] += 1

    def _report(self) -> None:
        late = self.late_us[: max(1, min(self.events, LATENESS_SAMPLES))]
        self.get_logger().info(
            f"published {self.stats['joint_states']} joint states, {self.stats['tracker_poses']} "
            f"tracker poses ({self.stats['dropped_by_beam_break']} lost to beam breaks); "
            f"publish lateness p50 {np.median(late):.0f} µs, p99 {np.percentile(late, 99):.0f} µs"
        )

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


def main(args: list[str] | None = None) -> int:
    def finish(node: SimCellNode) -> None:
        node.stop()
        node._report()

    return run_node("sim_cell_node", SimCellNode, SingleThreadedExecutor, args, on_exit=finish)


if __name__ == "__main__":
    sys.exit(main())
