"""The kinematics node: FK and IK services through the hybrid model, and the corrected pose of the robot.

An adapter only: it turns messages into core calls and results back into messages.

Three executors in three threads, all rclpy's EventsExecutor (the fastest here: a Trigger round trip
costs a fraction of what it does with the others, and it keeps up with high-rate topics where the
MultiThreadedExecutor drops messages). The node itself serves FK. A companion node, ``<name>_ik``,
serves ``<name>/compute_ik`` and ``<name>/reload``, so a long IK or a reload never blocks FK; another,
``<name>_pose``, turns joint states into ``<name>/corrected_pose``, so a burst of FK requests does not
queue the pose topic behind it.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from dataclasses import asdict

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from hybrid_kinematics_interfaces.srv import CompensateTrajectory, ComputeFK, ComputeIK
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.monitor import DriftMonitor, MonitorOptions, MonitorStatus
from hybrid_kinematics_ros.ik.compensate import MAX_JOINT_CORRECTION_RAD, compensate
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.solver import OTHER_BRANCH, IKOptions, IKResult, IKSolver
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics import approach
from hybrid_kinematics_ros.kinematics.approach import ApproachTracker
from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import resolve_path
from hybrid_kinematics_ros.kinematics.ur_kinematics import BASE_LINK as UR_BASE_LINK
from hybrid_kinematics_ros.kinematics.ur_kinematics import TIP_LINK as UR_TIP_LINK
from hybrid_kinematics_ros.kinematics.ur_kinematics import chain_from_ur_kinematics, ur_urdf
from hybrid_kinematics_ros.model import range_policy
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.range_policy import OUTSIDE
from hybrid_kinematics_ros.nodes.convert import (
    RequestError,
    joint_list_from_msg,
    joint_state_msg,
    joints_from_msg,
    joints_from_msg_lenient,
    matrix_from_msg,
    pose_msg_of_rows,
    pose_msgs,
    pose_with_covariance_msg,
    set_bounds,
    stamp_is_zero,
    stamp_ns,
    trajectory_arrays,
    trajectory_msg,
    transform_msg_of_pose,
)
from hybrid_kinematics_ros.nodes.process import freeze_heap, one_blas_thread
from hybrid_kinematics_ros.nodes.runtime import StartupError, read_only_parameter, run_node
from hybrid_kinematics_ros.nodes.stats import RequestStats

LOAD_ERRORS = (DataError, KinematicsError, ModelError, OSError)
MAX_SOLUTIONS = 16
SERVICE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _nearest_only(results: list[IKResult], max_solutions: int, options: IKOptions) -> bool:
    """Whether the answer is the nearest configuration found, out of reach: one solution asked for, none found,
    and the best beyond the tolerances (not refused for the calibrated range: that answer is no configuration
    to run)."""
    if max(1, max_solutions) != 1 or not results or results[0].success or results[0].q is None:
        return False
    best = results[0]
    return best.position_error_mm > options.position_tolerance_mm or (
        best.orientation_error_deg > options.orientation_tolerance_deg
    )


class KinematicsNode(Node):
    def __init__(self, name: str = "kinematics_node", **kwargs) -> None:
        super().__init__(name, **kwargs)
        topic, publish, diagnostics_period = self._declare_serving()
        monitor_topic, monitor_options = self._declare_monitor()
        self._lock = threading.Lock()
        self.model, self.solver = self._load()
        # A model trained with condition channels (hybrid-kinematics train --condition temperature) needs
        # their current values: parameters conditions.NAME, settable at run time; unset: the training mean,
        # which a WARN, the diagnostics and every answer's message say. The node keeps the values (with the
        # joints' approach directions) here, and every answer computes with a model of a snapshot of them taken
        # under the lock (HybridModel.with_conditions): the served model itself never changes.
        for name in self.model.condition_names:
            self.declare_parameter(f"conditions.{name}", float("nan"))
        self._conditions, self._unset = self._conditions_of(self.model)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.compensator = self._compensator(self.model)
        self._latest: np.ndarray | None = None
        self._approach: tuple[int, ApproachTracker] | None = None  # (the load it follows, its tracker)
        self._loads = 0  # models loaded: a reload starts the approach directions afresh, a new payload does not
        self._reply = threading.local()  # see _fk_pose
        self.stats = RequestStats()
        self._create_endpoints(topic, publish, diagnostics_period)
        self._monitor_options = monitor_options
        self.monitor = DriftMonitor(self.model, monitor_options) if monitor_options else None
        self._drifted = False
        if self.monitor is not None:
            tracker_qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
            self.pose_node.create_subscription(PoseStamped, monitor_topic, self._on_tracker_pose, tracker_qos)
        m = self.model
        kind = f"calibrated model {self.model_dir}" if m.is_corrected else "analytic URDF model (no model_dir)"
        self.get_logger().info(
            f"serving {kind}: {m.chain.base_link} -> {m.chain.tip_link}, joints {', '.join(m.joint_names)}; "
            f"IK: {self.solver.path}"
        )
        for warning in m.chain.inertial_warnings:
            self.get_logger().warn(f"URDF: {warning}")
        freeze_heap()  # no full collection of the loaded model inside a request (a stall past its budget)
        one_blas_thread()  # no BLAS pool spinning on the other core while a request waits for it

    def _declare(self, name: str, default, description: str):
        return read_only_parameter(self, name, default, description)

    def _declare_serving(self) -> tuple[str, bool, float]:
        """The parameters of what the node serves and how; the joint states' topic, whether to publish the
        corrected pose, and the diagnostics' period."""
        declare = self._declare
        self.model_dir = declare(
            "model_dir", "", "trained model directory (or package://pkg/path); empty: analytic URDF kinematics only"
        )
        self.urdf_path = declare("urdf_path", "", "URDF file or package://pkg/path (or give robot_description)")
        self.robot_description = declare("robot_description", "", "URDF text (used when urdf_path is empty)")
        self.ur_kinematics = declare(
            "ur_kinematics",
            "",
            "a UR's kinematics file (ur_calibration's, or package://pkg/path): the URDF is the one ur_description "
            "builds from it, on urdf_path's (or robot_description's) inertials and limits, else the embedded UR10's",
        )
        self.base_link = declare("base_link", "", "base link of the chain (default: the model's)")
        self.tip_link = declare("tip_link", "", "tip link of the chain (default: the model's)")
        topic = declare("joint_states_topic", "/joint_states", "joint states to turn into corrected poses")
        publish = declare("publish_corrected_pose", True, "publish ~/corrected_pose for each joint state")
        self.ik_timeout_ms = declare("ik_timeout_ms", 50.0, "time budget per IK solution")
        self.ik_request_budget_ms = declare(
            "ik_request_budget_ms",
            0.0,
            "total time budget of one IK request, all seeds and solutions (0: max_solutions x ik_timeout_ms)",
        )
        self.compensation_tolerance = (
            declare("compensation_tolerance_mm", 1e-5, "compensate_trajectory: hybrid FK vs the plan's URDF pose"),
            declare("compensation_tolerance_deg", 1e-5, "compensate_trajectory: orientation tolerance"),
        )
        self.max_joint_correction = declare(
            "max_joint_correction_rad",
            MAX_JOINT_CORRECTION_RAD,
            "compensate_trajectory: a larger correction of a point (a singularity, another branch) fails it",
        )
        torch_threads = declare(
            "torch_threads",
            1,
            "threads of torch's batched net inference; 0: torch's default (one per core, which on a busy machine "
            "with this node's three executor threads is 2-4x slower for a 1000-point trajectory)",
        )
        if torch_threads > 0:
            torch.set_num_threads(torch_threads)
        diagnostics_period = declare("diagnostics_period_s", 1.0, "period of /diagnostics (s); 0: off")
        self.range_policy = declare(
            "out_of_range_policy",
            "warn",
            f"outside the joint range the nets were trained on: {range_policy.described()}",
        )
        self.coverage_radius = declare(
            "coverage_radius_rad",
            0.0,
            "> 0: the calibrated range is where a training configuration lies within this distance (joint "
            "space, rad), instead of the trained joint ranges (hybrid-kinematics evaluate suggests one); 0: off",
        )
        self.gravity = declare(
            "gravity",
            [0.0, 0.0, 0.0],
            "m/s² in the base frame, for the parametric stage's joint torques (a wall or ceiling mount); "
            "0 0 0: the model's own (model.json, from the robot config it was trained with)",
        )
        # the payload the robot carries now, settable at run time (NaN: the model's, from model.json)
        self.declare_parameter("payload_mass", float("nan"))
        self.declare_parameter("payload_com", [float("nan")] * 3)
        return topic, publish, diagnostics_period

    def _declare_monitor(self) -> tuple[str, MonitorOptions | None]:
        """The tracker monitor's parameters: its topic and options (None: off)."""
        declare = self._declare
        monitor_topic = declare(
            "monitor_tracker_topic",
            "",
            "the tracker's live poses (geometry_msgs/PoseStamped): the node judges each still pose against the "
            "model and reports drift on /diagnostics; empty: off",
        )
        window = declare("monitor_window", 100, "judged poses the drift test looks back over")
        reference = declare("monitor_reference_poses", 20, "poses that place a tracker station the model does not know")
        still = declare("monitor_still_s", 0.2, "a still run of the joints this long gives one pose (s)")
        margin = declare(
            "monitor_clock_margin_s", 0.05, "tracker poses this close to a still run's ends are left out (s)"
        )
        try:
            options = MonitorOptions(window, reference, still, clock_margin_s=margin) if monitor_topic else None
        except CalibrationError as exc:
            raise StartupError(f"parameters monitor_*: {exc}") from exc
        return monitor_topic, options

    def _create_endpoints(self, topic: str, publish: bool, diagnostics_period: float) -> None:
        """The services, the corrected pose's publishers, the joint states' subscription and the diagnostics."""
        # Replies share one writer; with the default depth of 10, a burst from many clients can overwrite a
        # reply before a slow client has taken it, and that call is never answered.
        self.create_service(ComputeFK, "~/compute_fk", self._on_fk, qos_profile=SERVICE_QOS)
        # the slow services live on a companion node, spun by its own executor thread (see main)
        self.ik_node = Node(f"{self.get_name()}_ik", namespace=self.get_namespace(), context=self.context)
        own = self.get_fully_qualified_name()
        self.ik_node.create_service(ComputeIK, f"{own}/compute_ik", self._on_ik, qos_profile=SERVICE_QOS)
        self.ik_node.create_service(Trigger, f"{own}/reload", self._on_reload)
        self.ik_node.create_service(CompensateTrajectory, f"{own}/compensate_trajectory", self._on_compensate)
        self.pose_node = Node(f"{self.get_name()}_pose", namespace=self.get_namespace(), context=self.context)
        self.pose_pub = self.transform_pub = self.covariance_pub = None
        if publish:
            self.pose_pub = self.pose_node.create_publisher(PoseStamped, f"{own}/corrected_pose", QoSProfile(depth=100))
            # the same pose, naming the frame it places (the tip link): PoseStamped has no child frame
            self.transform_pub = self.pose_node.create_publisher(
                TransformStamped, f"{own}/corrected_transform", QoSProfile(depth=100)
            )
            # with its error bounds as a covariance, for a model that carries them (see docs/nodes.md)
            self.covariance_pub = self.pose_node.create_publisher(
                PoseWithCovarianceStamped, f"{own}/corrected_pose_with_covariance", QoSProfile(depth=100)
            )
        # best effort (matches reliable and best-effort publishers) with a deep queue for bursts
        joint_qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.pose_node.create_subscription(JointState, topic, self._on_joint_state, joint_qos)
        if diagnostics_period > 0:
            self.diag_pub = self.pose_node.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.pose_node.create_timer(diagnostics_period, self._publish_diagnostics)

    # ------------------------------------------------------------------ loading
    def _urdf(self) -> str | None:
        """The URDF the node serves without a model, or checks the model against: the one built from
        ``ur_kinematics`` when given (see :func:`_given_urdf` for its template), else the given one."""
        given = self._given_urdf()
        return ur_urdf(self.ur_kinematics, given) if self.ur_kinematics else given

    def _given_urdf(self) -> str | None:
        if self.urdf_path:
            path = resolve_path(self.urdf_path)
            if not path.is_file():
                where = "" if str(path) == self.urdf_path else f" ({path})"
                raise StartupError(f"parameter urdf_path: {self.urdf_path}{where} does not exist")
            return path.read_text(encoding="utf-8-sig")
        return self.robot_description or None

    def _analytic_chain(self) -> Chain:
        """The chain served without a model: ``ur_kinematics``'s (``base_link`` to ``tool0`` unless the
        parameters name other links), else the given URDF's between ``base_link`` and ``tip_link``."""
        if self.ur_kinematics:
            base, tip = self.base_link or UR_BASE_LINK, self.tip_link or UR_TIP_LINK
            return chain_from_ur_kinematics(self.ur_kinematics, self._given_urdf(), base, tip)
        urdf = self._given_urdf()
        if urdf is None or not self.base_link or not self.tip_link:
            raise StartupError(
                "give model_dir, or urdf_path (or robot_description) with base_link and tip_link, or ur_kinematics"
            )
        return chain_from_urdf(urdf, self.base_link, self.tip_link)

    def _load(self) -> tuple[HybridModel, IKSolver]:
        try:
            if self.model_dir:
                model = HybridModel.load(self.model_dir, expect_urdf=self._urdf())
                for name, value in (("base_link", self.base_link), ("tip_link", self.tip_link)):
                    if value and value != getattr(model.chain, name):
                        raise StartupError(
                            f"parameter {name} '{value}' differs from the model's '{getattr(model.chain, name)}'"
                        )
            else:
                model = HybridModel.analytic_only(self._analytic_chain())
            model = model.with_range_policy(self.range_policy)
            model = model.with_coverage_radius(self.coverage_radius if self.coverage_radius > 0 else None)
            gravity = np.asarray(self.gravity, dtype=float)
            if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
                raise StartupError(f"parameter gravity: {list(self.gravity)} is not three finite numbers (m/s²)")
            identified = ((model.manifest.get("parametric") or {}).get("payload") or {}).get("gravity")
            if np.any(gravity) and identified is not None and not np.allclose(gravity, identified):
                raise StartupError(
                    f"parameter gravity: {gravity.tolist()} differs from the {identified} m/s² the model's stage "
                    "was identified with; retrain with the robot config's gravity, or leave the parameter unset"
                )
            if np.any(gravity):
                model = model.with_gravity(gravity)
            model = self._carrying(
                model, self.get_parameter("payload_mass").value, self.get_parameter("payload_com").value
            )
        except LOAD_ERRORS as exc:
            raise StartupError(str(exc)) from exc
        return model, self._solver(model)

    def _conditions_of(self, model: HybridModel) -> tuple[np.ndarray, list[str]]:
        """The condition values ``model`` serves with (its defaults, then the conditions.* parameters), and
        the channels no parameter sets (approach directions aside: the joint states set those)."""
        unset = []
        for name in model.condition_names:
            key = f"conditions.{name}"
            value = self.get_parameter(key).value if self.has_parameter(key) else float("nan")
            if value is not None and np.isfinite(value):
                model = model.with_condition(name, float(value))
            elif not approach.is_channel(name):
                unset.append(name)
        values = model.condition_values.copy()
        for name in unset:
            self.get_logger().warning(
                f"parameter conditions.{name} is not set: the model uses its training mean "
                f"{model.condition_defaults[name]:g}; set it to the cell's current value"
            )
        return values, unset

    def _unset_note(self) -> str:
        """What every answer's message says while a condition channel is unset."""
        defaults = self.model.condition_defaults
        return "".join(
            f"; conditions.{name} is not set, its training mean {defaults[name]:g} is used" for name in self._unset
        )

    def _carrying(self, model: HybridModel, mass: float, com) -> HybridModel:
        """``model`` with the payload parameters' payload (NaN mass: as trained; a NaN in the centre of mass:
        the trained one)."""
        if mass is None or not np.isfinite(mass):
            return model
        com = np.asarray(com, dtype=float)
        if com.shape == (3,) and np.any(np.isnan(com)):
            com = model.trained_payload[1]
        carrying = model.with_payload(float(mass), com)
        if carrying.payload_changed and carrying.nets:
            self.get_logger().warning(
                f"payload {mass:g} kg: the parametric stage follows it, the nets were trained with another, so "
                "every answer is flagged outside the calibrated range"
            )
        return carrying

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """Every change is checked before any is applied; then the model (a new payload), its solvers and
        the condition values are swapped together, under the lock, unless a reload came in between."""
        given = {p.name: p.value for p in params}
        model = self.model
        try:
            serving = model
            if "payload_mass" in given or "payload_com" in given:
                mass = given.get("payload_mass", self.get_parameter("payload_mass").value)
                com = given.get("payload_com", self.get_parameter("payload_com").value)
                if "payload_mass" in given and (mass is None or not np.isfinite(mass)):
                    raise ModelError("give a number of kg (reload the node to serve the trained payload again)")
                serving = self._carrying(model, mass, com)
            conditions = {n.removeprefix("conditions."): v for n, v in given.items() if n.startswith("conditions.")}
            with self._lock:
                values = self._conditions.copy()
            checked = serving.with_conditions(values)  # each value checked by the model
            for name, value in conditions.items():
                checked = checked.with_condition(name, float(value))
            values = checked.condition_values.copy()
        except (ModelError, TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        solvers = (self._solver(serving), self._compensator(serving)) if serving is not model else None
        with self._lock:
            if self.model is not model:
                return SetParametersResult(successful=False, reason="the model was reloaded meanwhile; set it again")
            if solvers is not None:
                self.model, (self.solver, self.compensator) = serving, solvers
                if self.monitor is not None:  # another payload: its model is judged afresh
                    self.monitor, self._drifted = DriftMonitor(serving, self._monitor_options), False
            self._conditions = values
            self._unset = [n for n in self._unset if n not in conditions]
        return SetParametersResult(successful=True)

    def _snapshot(self) -> tuple[HybridModel, IKSolver, IKSolver, np.ndarray]:
        """The served model, its solvers and a copy of the condition values, taken together under the lock."""
        with self._lock:
            return self.model, self.solver, self.compensator, self._conditions.copy()

    def _solver(self, model: HybridModel) -> IKSolver:
        options = IKOptions(timeout_s=self.ik_timeout_ms / 1e3, require_calibrated_range=self.range_policy == "refuse")
        return IKSolver(model, options).warm_up()

    def _compensator(self, model: HybridModel) -> IKSolver:
        """The IK of compensate_trajectory: the node's options with the compensation's tolerances."""
        mm, deg = self.compensation_tolerance
        options = IKOptions(
            timeout_s=self.ik_timeout_ms / 1e3,
            require_calibrated_range=self.range_policy == "refuse",
            position_tolerance_mm=mm,
            orientation_tolerance_deg=deg,
        )
        return IKSolver(model, options).warm_up()

    # ------------------------------------------------------------------ callbacks
    def _on_joint_state(self, msg: JointState) -> None:
        try:
            self._corrected_pose(msg)
        except Exception as exc:  # one bad message must not end the topic
            self.get_logger().error(
                f"corrected_pose: internal error ({type(exc).__name__}): {exc}", throttle_duration_sec=5.0
            )

    def _corrected_pose(self, msg: JointState) -> None:
        model = self.model
        q = joints_from_msg_lenient(msg, model.joint_names)
        if q is None:
            self.get_logger().warn(
                f"joint states lack some of {', '.join(model.joint_names)}; no corrected pose",
                throttle_duration_sec=5.0,
            )
            return
        self._latest = q
        with self._lock:
            model, values = self.model, self._conditions
            # a model with approach inputs follows the joints' directions of motion (a reload starts afresh)
            if model.approach_index is not None:
                if self._approach is None or self._approach[0] != self._loads:
                    self._approach = (self._loads, ApproachTracker(len(q)))
                values[model.approach_index] = self._approach[1].update(q)
            values = values.copy()
        if self.pose_pub is not None:
            self._publish_corrected_pose(model.with_conditions(values), q, msg)
        monitor = self.monitor
        if monitor is not None:
            try:
                self._watch(monitor.joints(stamp_ns(msg.header.stamp), q, values))
            except (CalibrationError, ModelError) as exc:
                self.get_logger().error(f"tracker monitor: {exc}", throttle_duration_sec=5.0)

    def _on_tracker_pose(self, msg: PoseStamped) -> None:
        p, o = msg.pose.position, msg.pose.orientation
        try:
            self.monitor.tracker(stamp_ns(msg.header.stamp), [p.x, p.y, p.z], [o.x, o.y, o.z, o.w], msg.header.frame_id)
        except CalibrationError as exc:
            self.get_logger().error(f"tracker monitor: {exc}", throttle_duration_sec=5.0)

    def _watch(self, status: MonitorStatus | None) -> None:
        """Log the monitor's verdict when it changes."""
        if status is None or status.drifted == self._drifted:
            return
        self._drifted = status.drifted
        if status.drifted:
            self.get_logger().warn(status.message() + ": verify the model (hybrid-kinematics verify) or update it")
        else:
            self.get_logger().info(status.message())

    def _publish_corrected_pose(self, model: HybridModel, q: np.ndarray, msg: JointState) -> None:
        if model.range_policy == "refuse" and model.nets and not model.in_calibrated_range(q)[0]:
            self.get_logger().warn(
                f"no corrected pose outside the calibrated range ({model.describe_outside(q)})",
                throttle_duration_sec=5.0,
            )
            return
        rows = model.fk_rows(q.tolist())
        pose = pose_msg_of_rows(rows, model.chain.base_link, msg.header.stamp)
        self.pose_pub.publish(pose)
        self.transform_pub.publish(transform_msg_of_pose(pose, model.chain.tip_link))
        bounds = model.error_bounds(q) if self.covariance_pub.get_subscription_count() else None
        if bounds is not None:
            position, orientation = bounds
            self.covariance_pub.publish(
                pose_with_covariance_msg(
                    pose, float(position[0]), None if orientation is None else float(orientation[0]), model.bounds.level
                )
            )

    def _on_fk(self, request: ComputeFK.Request, response: ComputeFK.Response) -> ComputeFK.Response:
        """The round trip costs a few hundred µs in rclpy alone and the process wakes up with cold caches,
        where each numpy call costs microseconds: one configuration takes a path of few numpy calls."""
        start = time.perf_counter()
        model, _, _, values = self._snapshot()
        return self._fk(request, response, model.with_conditions(values), start)

    def _fk(self, request: ComputeFK.Request, response: ComputeFK.Response, model: HybridModel, start: float):
        try:
            states, names = request.joint_states, model.joint_names
            if not states:
                raise RequestError("joint_states is empty; send at least one configuration")
            analytic = request.analytic_only
            if len(states) == 1:
                q = joint_list_from_msg(states[0], names, "joint_states[0]")
                if not analytic:
                    model.check_range(q)
                stamp = states[0].header.stamp
                if stamp_is_zero(stamp):
                    stamp = self.get_clock().now().to_msg()
                rows = model.fk_rows(q, analytic=analytic)
                response.poses = [pose_msg_of_rows(rows, model.chain.base_link, stamp, out=self._fk_pose())]
                response.in_calibrated_range = [model.in_calibrated_range_one(q)]
                if not analytic:
                    set_bounds(response, model, q)
            else:
                q = np.array([joints_from_msg(js, names, f"joint_states[{i}]") for i, js in enumerate(states)])
                if not analytic:
                    model.check_range(q)
                stamps = [js.header.stamp for js in states]
                if any(stamp_is_zero(stamp) for stamp in stamps):
                    now = self.get_clock().now().to_msg()
                    stamps = [now if stamp_is_zero(stamp) else stamp for stamp in stamps]
                response.poses = pose_msgs(model.fk(q, analytic=analytic), model.chain.base_link, stamps)
                response.in_calibrated_range = model.in_calibrated_range(q).tolist()
                if not analytic:
                    set_bounds(response, model, q)
            response.success = True
            response.message = (
                "ok"
                if not model.nets or all(response.in_calibrated_range)
                else f"some configurations lie outside the calibrated joint range; {OUTSIDE[model.range_policy]}"
            ) + self._unset_note()
        except (RequestError, KinematicsError, ModelError) as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # a bug must cost one answer, never the service
            self._unexpected("compute_fk", exc, response)
        outside = response.in_calibrated_range.count(False) if response.success and model.nets else 0
        self.stats.record("fk", time.perf_counter() - start, response.success, outside)
        return response

    def _fk_pose(self) -> PoseStamped:
        """The reply pose of one-configuration FK, one message per executor thread, overwritten by each call.
        Safe because a synchronous service callback's response is serialized on its thread before that
        thread runs the next callback."""
        pose = getattr(self._reply, "pose", None)
        if pose is None:
            pose = self._reply.pose = PoseStamped()
        return pose

    def _unexpected(self, service: str, exc: Exception, response) -> None:
        """Any other exception: answer success=false with its message and keep serving."""
        response.success = False
        response.message = f"internal error ({type(exc).__name__}): {exc}"
        self.get_logger().error(f"{service}: {response.message}", throttle_duration_sec=1.0)

    def _on_ik(self, request: ComputeIK.Request, response: ComputeIK.Response) -> ComputeIK.Response:
        start = time.perf_counter()
        model, solver, _, values = self._snapshot()
        model = model.with_conditions(values)
        return self._ik(request, response, model, solver.with_model(model), start)

    def _ik(
        self,
        request: ComputeIK.Request,
        response: ComputeIK.Response,
        model: HybridModel,
        solver: IKSolver,
        start: float,
    ) -> ComputeIK.Response:
        nearest = False  # out of reach: the nearest configuration found is returned, with success false
        try:
            target, seed = self._ik_target(request, model)
            results = self._ik_results(request, target, seed, solver, start)
            nearest = _nearest_only(results, int(request.max_solutions), solver.options)
            self._fill_ik(response, request, model, results, nearest)
        except (RequestError, IKError, KinematicsError, ModelError) as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # a bug must cost one answer, never the service
            self._unexpected("compute_ik", exc, response)
        if not response.success and not nearest:
            response.solutions, response.position_error_mm, response.orientation_error_deg = [], [], []
            response.in_calibrated_range, response.position_bound_mm, response.orientation_bound_deg = [], [], []
        outside = response.in_calibrated_range.count(False) if model.nets else 0
        self.stats.record("ik", time.perf_counter() - start, response.success, outside)
        return response

    def _ik_target(self, request: ComputeIK.Request, model: HybridModel) -> tuple[np.ndarray, np.ndarray | None]:
        """The request's target in the base frame, and its seed (the latest joint states without one)."""
        frames = [model.chain.base_link, *(f for f in model.chain.link_frames if f != model.chain.base_link)]
        target = matrix_from_msg(request.target, frames)
        if request.seed.position or request.seed.name:
            seed = joints_from_msg(request.seed, model.joint_names, "seed")
        else:
            seed = self._latest
        frame = request.target.header.frame_id
        if frame not in ("", model.chain.base_link):  # a link's pose at the seed (where the robot is)
            if seed is None:
                raise RequestError(
                    f"a target in frame '{frame}' is relative to where that link is: give a seed, or "
                    "publish joint states"
                )
            target = model.link_pose(frame, seed, analytic=request.analytic_only) @ target
        return target, seed

    def _ik_results(
        self, request: ComputeIK.Request, target: np.ndarray, seed: np.ndarray | None, solver: IKSolver, start: float
    ) -> list[IKResult]:
        """One solution, or up to ``max_solutions`` within the request's budget from ``start``."""
        k = max(1, int(request.max_solutions))
        if k > MAX_SOLUTIONS:
            raise RequestError(f"max_solutions {k} is above the limit of {MAX_SOLUTIONS}")
        if k == 1:
            return [solver.solve(target, seed, analytic=request.analytic_only)]
        extra = [self._latest] if self._latest is not None and seed is not self._latest else []
        budget_ms = self.ik_request_budget_ms if self.ik_request_budget_ms > 0 else k * self.ik_timeout_ms
        deadline = start + budget_ms / 1e3
        return solver.solve_many(target, seed, k, extra, analytic=request.analytic_only, deadline=deadline)

    def _fill_ik(
        self,
        response: ComputeIK.Response,
        request: ComputeIK.Request,
        model: HybridModel,
        results: list[IKResult],
        nearest: bool,
    ) -> None:
        """The successful ``results`` into ``response`` (or the nearest configuration alone, if ``nearest``)."""
        good = [r for r in results if r.success]
        shown = results[:1] if nearest else good
        now = self.get_clock().now().to_msg()
        response.solutions = [joint_state_msg(r.q, model.joint_names, now) for r in shown]
        response.position_error_mm = [float(r.position_error_mm) for r in shown]
        response.orientation_error_deg = [float(r.orientation_error_deg) for r in shown]
        response.in_calibrated_range = [bool(r.in_calibrated_range) for r in shown]
        if shown and not request.analytic_only:
            set_bounds(response, model, np.array([r.q for r in shown]))
        response.success = bool(good)
        if good:
            response.message = f"{len(good)} solution(s)" + self._unset_note()
            if good[0].stats.get("other_branch"):
                response.message += f"; {OTHER_BRANCH}"
        else:
            response.message = (
                results[0].message if results else "no solution found from any seed within the time budget"
            )
        if nearest:
            response.message += "; solutions[0] is the nearest configuration found"

    def _on_compensate(
        self, request: CompensateTrajectory.Request, response: CompensateTrajectory.Response
    ) -> CompensateTrajectory.Response:
        """The corrected trajectory; on failure, the points before ``failed_index``."""
        model, _, solver, values = self._snapshot()
        model = model.with_conditions(values)
        return self._compensate(request, response, model, solver.with_model(model))

    def _compensate(
        self,
        request: CompensateTrajectory.Request,
        response: CompensateTrajectory.Response,
        model: HybridModel,
        solver: IKSolver,
    ) -> CompensateTrajectory.Response:
        response.failed_index = -1
        try:
            q, t, qd, qdd = trajectory_arrays(request.trajectory, model.joint_names)
            result = compensate(
                solver,
                q,
                t,
                qd,
                qdd,
                require_calibrated_range=model.range_policy == "refuse",
                max_joint_correction_rad=self.max_joint_correction,
            )
            keep = len(q) if result.success else result.failed_index
            response.trajectory = trajectory_msg(
                request.trajectory,
                model.joint_names,
                result.positions[:keep],
                None if result.velocities is None else result.velocities[:keep],
                None if result.accelerations is None else result.accelerations[:keep],
            )
            # every per-point array covers the points returned (the failed one's error is in the message)
            response.position_error_mm = result.position_error_mm[:keep].tolist()
            response.orientation_error_deg = result.orientation_error_deg[:keep].tolist()
            response.in_calibrated_range = result.in_calibrated_range[:keep].tolist()
            if keep:
                set_bounds(response, model, result.positions[:keep])
            response.failed_index = result.failed_index
            response.success = result.success
            outside = int(np.sum(~result.in_calibrated_range)) if model.nets else 0
            response.message = (
                result.message
                if not result.success
                else f"{len(q)} points corrected" + (f"; {outside} outside the calibrated range" if outside else "")
            )
        except (RequestError, IKError, KinematicsError, ModelError) as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # a bug must cost one answer, never the service
            self._unexpected("compensate_trajectory", exc, response)
        return response

    def _on_reload(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Load ``model_dir`` again; on failure the old model keeps serving."""
        try:
            model, solver = self._load()
        except Exception as exc:  # StartupError, or a bug: either way the old model serves on
            detail = str(exc) if isinstance(exc, StartupError) else f"internal error ({type(exc).__name__}): {exc}"
            response.success, response.message = False, f"reload failed, still serving the old model: {detail}"
            self.get_logger().error(response.message)
            return response
        compensator = self._compensator(model)
        conditions, unset = self._conditions_of(model)
        with self._lock:
            self.model, self.solver, self.compensator = model, solver, compensator
            self._conditions, self._unset = conditions, unset
            self._loads += 1
            if self.monitor is not None:  # a new model is judged afresh
                self.monitor, self._drifted = DriftMonitor(model, self._monitor_options), False
        freeze_heap()
        response.success, response.message = True, f"reloaded {self.model_dir or 'the URDF model'}"
        self.get_logger().info(response.message)
        return response

    def _publish_diagnostics(self) -> None:
        model = self.model
        values = {
            "model": str(self.model_dir) if self.model_dir else "analytic URDF model",
            "chain": f"{model.chain.base_link} -> {model.chain.tip_link}",
            "range_policy": model.range_policy,
            "coverage_radius_rad": str(model.coverage_radius or 0.0),
            **self.stats.snapshot(),
        }
        note = self._unset_note()
        if self._unset:
            values["conditions_unset"] = ", ".join(self._unset)
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if note else DiagnosticStatus.OK,
            name=f"{self.get_name()}: hybrid kinematics",
            hardware_id=model.chain.base_link,
            message=("calibrated model" if model.is_corrected else "analytic URDF model") + note,
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )
        statuses = [status]
        if self.monitor is not None:
            watch = self.monitor.status()
            statuses.append(
                DiagnosticStatus(
                    level=DiagnosticStatus.WARN if watch.drifted else DiagnosticStatus.OK,
                    name=f"{self.get_name()}: tracker monitor",
                    hardware_id=model.chain.base_link,
                    message=watch.message(),
                    values=[KeyValue(key=k, value=str(v)) for k, v in asdict(watch).items()],
                )
            )
        msg = DiagnosticArray(status=statuses)
        msg.header.stamp = self.pose_node.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    @property
    def companions(self) -> tuple[Node, Node]:
        """The nodes that need executors of their own (see the module docstring)."""
        return self.ik_node, self.pose_node

    def destroy_node(self) -> None:
        for companion in self.companions:
            companion.destroy_node()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """SIGINT and SIGTERM end both spin loops (EventsExecutor.spin() would ignore them here)."""
    from rclpy.experimental import EventsExecutor

    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())

    def spin_loop(executor) -> None:
        """The callbacks answer every exception themselves; this guard is the last line, so that a thread
        never ends while the others serve (a node half-deaf)."""
        while rclpy.ok() and not stopping.is_set():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception as exc:
                if not rclpy.ok() or stopping.is_set():
                    break
                rclpy.logging.get_logger("kinematics_node").error(f"spin: {type(exc).__name__}: {exc}")

    def spin(executor) -> None:
        node = executor.get_nodes()[0]
        others = []
        for companion in node.companions:
            other = EventsExecutor()
            other.add_node(companion)
            thread = threading.Thread(target=spin_loop, args=(other,), name=companion.get_name(), daemon=True)
            thread.start()
            others.append((other, thread))
        try:
            spin_loop(executor)
        finally:
            stopping.set()
            for other, thread in others:
                thread.join(timeout=5.0)
                other.shutdown()

    return run_node(
        "kinematics_node",
        KinematicsNode,
        EventsExecutor,
        args,
        spin=spin,
        signal_handler_options=rclpy.signals.SignalHandlerOptions.NO,
    )


if __name__ == "__main__":
    sys.exit(main())
