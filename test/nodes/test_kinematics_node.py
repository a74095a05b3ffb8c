"""The kinematics node as ros2 run starts it: real services, real topics, bad requests, reload."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from scipy.stats import chi2
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from hybrid_kinematics_interfaces.srv import ComputeFK, ComputeIK
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.nodes.convert import joint_state_msg, pose_msg
from test.nodes.rosutil import Client, start, stop

pytestmark = pytest.mark.ros
NODE = "/kinematics_node"


@pytest.fixture(scope="module")
def ros():
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture(scope="module")
def served(ros, trained, tmp_path_factory):
    """The node serving a copy of the trained model, and a client."""
    model_dir = tmp_path_factory.mktemp("served") / "model"
    shutil.copytree(trained[0], model_dir)
    log = model_dir.parent / "node.log"
    proc = start("kinematics_node", "-p", f"model_dir:={model_dir}", log=log)
    client = Client()
    try:
        fk = client.service(ComputeFK, f"{NODE}/compute_fk")
        ik = client.service(ComputeIK, f"{NODE}/compute_ik")
        reload = client.service(Trigger, f"{NODE}/reload")
        yield client, fk, ik, reload, trained[1], model_dir, proc
    finally:
        client.close()
        assert stop(proc) == 0, log.read_text()


def fk_request(qs, names, analytic=False):
    req = ComputeFK.Request()
    req.joint_states = [joint_state_msg(q, names, rclpy.time.Time().to_msg()) for q in qs]
    req.analytic_only = analytic
    return req


def poses_of(response):
    return np.array(
        [
            se3.matrix_from_pose(
                [p.pose.position.x, p.pose.position.y, p.pose.position.z],
                [p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w],
            )[0]
            for p in response.poses
        ]
    )


def test_fk_matches_the_core(served):
    client, fk, _, _, model, _, _ = served
    q = np.random.default_rng(0).uniform(model.trained_lower, model.trained_upper, (50, 6))
    resp = client.call(fk, fk_request(q, model.joint_names))
    assert resp.success, resp.message
    np.testing.assert_allclose(poses_of(resp), model.fk(q), atol=1e-9)
    assert resp.in_calibrated_range == [True] * 50
    assert {p.header.frame_id for p in resp.poses} == {"base_link"}
    # every pose with its error bounds, as the core gives them (mm, deg)
    position, orientation = model.error_bounds(q)
    np.testing.assert_allclose(resp.position_bound_mm, 1e3 * position, rtol=1e-12)
    np.testing.assert_allclose(resp.orientation_bound_deg, np.degrees(orientation), rtol=1e-12)
    one = client.call(fk, fk_request(q[:1], model.joint_names))
    np.testing.assert_allclose(poses_of(one)[0], model.fk_single(q[0]), atol=1e-9)
    np.testing.assert_allclose(one.position_bound_mm, 1e3 * position[:1], rtol=1e-12)
    analytic = client.call(fk, fk_request(q[:3], model.joint_names, analytic=True))
    np.testing.assert_allclose(poses_of(analytic), model.fk(q[:3], analytic=True), atol=1e-9)
    assert len(analytic.position_bound_mm) == 0 and len(analytic.orientation_bound_deg) == 0  # the URDF's: none
    # names select and order the joints
    order = [3, 1, 0, 5, 4, 2]
    shuffled = client.call(fk, fk_request(q[:2, order], [model.joint_names[i] for i in order]))
    np.testing.assert_allclose(poses_of(shuffled), model.fk(q[:2]), atol=1e-9)
    outside = client.call(fk, fk_request([model.trained_upper + 0.05], model.joint_names))
    assert outside.success and outside.in_calibrated_range == [False]


def ik_request(T, seed=None, names=(), k=1):
    req = ComputeIK.Request()
    req.target = pose_msg(T, "base_link", rclpy.time.Time().to_msg())
    if seed is not None:
        req.seed = joint_state_msg(seed, names, rclpy.time.Time().to_msg())
    req.max_solutions = k
    return req


def test_ik_single_and_several_solutions(served):
    client, _, ik, _, model, _, _ = served
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    T = model.fk(q)[0]
    resp = client.call(ik, ik_request(T, q + 0.05, model.joint_names))
    assert resp.success, resp.message
    solution = np.array(resp.solutions[0].position)
    pos, rot = se3.pose_errors(model.fk_single(solution), T)
    assert pos < 1e-4 and rot < 1e-4
    assert resp.position_error_mm[0] == pytest.approx(pos, abs=1e-9)
    assert resp.position_bound_mm[0] == pytest.approx(1e3 * model.error_bounds(solution)[0][0], rel=1e-12)
    many = client.call(ik, ik_request(T, q, model.joint_names, k=8))
    assert many.success and len(many.solutions) >= 2
    assert len(many.position_bound_mm) == len(many.orientation_bound_deg) == len(many.solutions)
    dists = [np.linalg.norm(np.array(s.position) - q) for s in many.solutions]
    assert dists == sorted(dists)


def test_ik_targets_in_the_chains_links_are_relative_to_where_they_are(served):
    """A target in ``tool0`` (1 cm along the tool's z, turned 0.1 rad about it) or in a link between the
    joints, taken at the seed; a target in another frame is refused, naming the chain's links. The
    frame used to be refused unless it was the base."""
    client, _, ik, _, model, _, _ = served
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    step = se3.from_rotvec([0.0, 0.0, 0.1], [0.0, 0.0, 0.01])[0]
    req = ik_request(step, q, model.joint_names)
    req.target.header.frame_id = "tool0"
    resp = client.call(ik, req)
    assert resp.success, resp.message
    pos, rot = se3.pose_errors(model.fk_single(np.array(resp.solutions[0].position)), model.fk_single(q) @ step)
    assert pos < 1e-4 and rot < 1e-4
    # analytic_only: relative to where the URDF model puts tool0 (it was the hybrid pose, millimetres off: a
    # "stay where you are" target moved the URDF tool by the calibration's correction)
    req = ik_request(np.eye(4), q, model.joint_names)
    req.target.header.frame_id, req.analytic_only = "tool0", True
    resp = client.call(ik, req)
    assert resp.success, resp.message
    np.testing.assert_allclose(resp.solutions[0].position, q, atol=1e-7)
    link_3 = fk.joint_frames(model.chain, q[None])[0, 2]  # link_3 moves with joint 3
    goal = model.fk_single(q + 0.02)
    req = ik_request(np.linalg.inv(link_3) @ goal, q, model.joint_names)
    req.target.header.frame_id = "link_3"
    resp = client.call(ik, req)
    assert resp.success, resp.message
    assert se3.pose_errors(model.fk_single(np.array(resp.solutions[0].position)), goal)[0] < 1e-4
    req.target.header.frame_id = "world"
    resp = client.call(ik, req)
    assert not resp.success and "'world', which is not a link of the chain" in resp.message
    assert "tool0" in resp.message


BAD_FK = {
    "NaN": (lambda names: fk_request([[np.nan, 0, 0, 0, 0, 0]], names), "NaN"),
    "count": (lambda names: fk_request([[0, 0, 0]], []), "3 positions and no names"),
    "unknown": (lambda names: fk_request([[0] * 6], [*names[:5], "elbow"]), "unknown joint(s) elbow"),
    "duplicate": (lambda names: fk_request([[0] * 6], [*names[:5], names[0]]), "more than once"),
    "empty": (lambda names: ComputeFK.Request(), "joint_states is empty"),
}


def test_bad_fk_requests_and_the_node_keeps_serving(served):
    client, fk, _, _, model, _, _ = served
    good = fk_request([np.zeros(6)], model.joint_names)
    for name, (make, message) in BAD_FK.items():
        resp = client.call(fk, make(model.joint_names))
        assert not resp.success, name
        assert message in resp.message, (name, resp.message)
        assert client.call(fk, good).success


def test_bad_ik_requests_and_the_node_keeps_serving(served):
    client, fk, ik, _, model, _, _ = served
    T = model.fk(np.array([0.1, -1.0, 1.0, -1.0, 1.0, 0.0]))[0]
    cases = []
    req = ik_request(T)
    req.target.pose.orientation.w = 2.0
    cases.append((req, "not a unit quaternion"))
    req = ik_request(T)
    req.target.pose.orientation.x = req.target.pose.orientation.y = 0.0
    req.target.pose.orientation.z = req.target.pose.orientation.w = 0.0
    cases.append((req, "not a unit quaternion (norm 0)"))
    req = ik_request(T)
    req.target.header.frame_id = "world"
    cases.append((req, "in frame 'world', which is not a link"))
    req = ik_request(T)
    req.target.pose.position.x = float("nan")
    cases.append((req, "NaN"))
    far = T.copy()
    far[:3, 3] = [4.0, 0.0, 0.0]
    cases.append((ik_request(far), "no solution"))
    cases.append((ik_request(T, np.zeros(4), ()), "4 positions and no names"))
    for req, message in cases:
        resp = client.call(ik, req, timeout=60)
        assert not resp.success and message in resp.message, resp.message
        assert client.call(fk, fk_request([np.zeros(6)], model.joint_names)).success
    assert client.call(ik, ik_request(T)).success


def test_an_unreachable_target_gets_the_nearest_configuration_and_its_distance(served):
    """0.3 m beyond the stretched arm: success false, and solutions[0] is the configuration that comes
    nearest, its errors the distance the hybrid FK measures from there to the target."""
    client, _, ik, _, model, _, _ = served
    q = np.array([0.2, -1.0, 0.4, -0.8, 1.1, 0.2])
    T = model.fk(q)[0]
    T[:3, 3] *= 1.0 + 0.3 / np.linalg.norm(T[:3, 3])
    resp = client.call(ik, ik_request(T, q, model.joint_names), timeout=60)
    assert not resp.success and "nearest configuration" in resp.message, resp.message
    assert len(resp.solutions) == 1 and resp.position_error_mm[0] > 100.0
    reached = model.fk(np.array(resp.solutions[0].position))[0]
    assert np.linalg.norm(reached[:3, 3] - T[:3, 3]) * 1e3 == pytest.approx(resp.position_error_mm[0], rel=1e-6)
    # several solutions asked for: none, and no configuration passed off as one
    many = client.call(ik, ik_request(T, q, model.joint_names, k=4), timeout=60)
    assert not many.success and not many.solutions


def test_corrected_pose_topic_rate_and_stamps(served):
    client, _, _, _, model, _, _ = served
    received, transforms, covariances = [], [], []
    sub = client.node.create_subscription(PoseStamped, f"{NODE}/corrected_pose", received.append, 100)
    companion = client.node.create_subscription(TransformStamped, f"{NODE}/corrected_transform", transforms.append, 100)
    with_cov = client.node.create_subscription(
        PoseWithCovarianceStamped, f"{NODE}/corrected_pose_with_covariance", covariances.append, 100
    )
    pub = client.node.create_publisher(JointState, "/joint_states", 100)
    deadline = time.monotonic() + 30.0
    subs = (sub, companion, with_cov)
    while (
        pub.get_subscription_count() < 1 or min(s.get_publisher_count() for s in subs) < 1
    ) and time.monotonic() < deadline:
        client.spin_for(0.1)  # discovery: both ends matched before anything is sent
    client.spin_for(0.5)
    sent = {}
    q = np.array([0.2, -1.1, 1.2, -0.8, 1.0, 0.3])
    start_time = time.monotonic()
    n = 220  # 2 s at 110 Hz
    for i in range(n):
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + i, 7
        msg.name = [*model.joint_names, "gripper"]  # extra joints are ignored
        msg.position = [*(q + 1e-3 * i), 0.5]
        sent[(1000 + i, 7)] = q + 1e-3 * i
        pub.publish(msg)
        client.spin_for(max(0.0, start_time + (i + 1) / 110.0 - time.monotonic()))
    client.spin_for(1.0)
    assert len(received) >= 0.95 * n
    for msg in received:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        assert key in sent
        T = model.fk_single(sent[key])
        assert abs(msg.pose.position.x - T[0, 3]) < 1e-9
    # the companion names the frame it places: the same poses, from the base link to the tip link
    assert len(transforms) >= 0.95 * n
    poses = {(m.header.stamp.sec, m.header.stamp.nanosec): m.pose for m in received}
    for msg in transforms:
        assert (msg.header.frame_id, msg.child_frame_id) == (model.chain.base_link, model.chain.tip_link)
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if key in poses:
            assert msg.transform.translation.z == poses[key].position.z
            assert msg.transform.rotation.w == poses[key].orientation.w
        T = model.fk_single(sent[key])
        assert abs(msg.transform.translation.y - T[1, 3]) < 1e-9
    # and with its error bounds as the covariance of a Gaussian whose error norm stays under them at 95 %
    assert len(covariances) >= 0.95 * n
    scale = chi2.ppf(model.bounds.level, 3)
    for msg in covariances:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        assert abs(msg.pose.pose.position.x - model.fk_single(sent[key])[0, 3]) < 1e-9
        cov = np.array(msg.pose.covariance).reshape(6, 6)
        position, orientation = model.error_bounds(sent[key])
        np.testing.assert_allclose(
            np.diag(cov), np.r_[[position[0] ** 2 / scale] * 3, [orientation[0] ** 2 / scale] * 3]
        )
        assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_reload_is_atomic(served):
    client, fk, _, reload, model, model_dir, _ = served
    good = fk_request([np.full(6, 0.1)], model.joint_names)
    before = poses_of(client.call(fk, good))
    backup = (model_dir / "position.pt").read_bytes()
    (model_dir / "position.pt").write_bytes(b"corrupt")
    try:
        resp = client.call(reload, Trigger.Request())
        assert not resp.success and "position.pt is corrupt" in resp.message
        np.testing.assert_array_equal(poses_of(client.call(fk, good)), before)
    finally:
        (model_dir / "position.pt").write_bytes(backup)
    assert client.call(reload, Trigger.Request()).success
    np.testing.assert_allclose(poses_of(client.call(fk, good)), before, atol=1e-12)


def test_refuses_to_start_for_another_urdf(ros, trained, tmp_path):
    log = tmp_path / "node.log"
    proc = start(
        "kinematics_node", "-p", f"model_dir:={trained[0]}", "-p", f"urdf_path:={CONFIG_DIR / 'rx160.urdf'}", log=log
    )
    assert proc.wait(60) == 1
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    assert len(lines) == 1 and "trained for another URDF" in lines[0] and "FATAL" in lines[0]


def test_in_process_node_with_defaults_file(ros):
    """config/kinematics.yaml's parameters as they are (the URDF as a package:// path) serve the embedded UR10."""
    import yaml

    from hybrid_kinematics_ros.nodes.kinematics_node import KinematicsNode

    params = yaml.safe_load((CONFIG_DIR / "kinematics.yaml").read_text())["kinematics_node"]["ros__parameters"]
    assert params["urdf_path"].startswith("package://hybrid_kinematics_ros/")
    overrides = [rclpy.parameter.Parameter(k, value=v) for k, v in params.items()]
    node = KinematicsNode("kinematics_in_process", parameter_overrides=overrides)
    client = Client("in_process_client")
    client.executor.add_node(node)  # one executor spins the node and its client
    try:
        fk = client.service(ComputeFK, "/kinematics_in_process/compute_fk")
        resp = client.call(fk, fk_request([np.zeros(6)], node.model.joint_names))
        assert resp.success
        np.testing.assert_allclose(poses_of(resp)[0], node.model.fk_single(np.zeros(6)), atol=1e-12)
    finally:
        client.close()
        node.destroy_node()


@pytest.mark.parametrize("policy", ["refuse", "parametric", "bound"])
def test_out_of_range_policy(ros, trained, policy):
    """Outside the trained joint range the node refuses, falls back to the model without the nets, or serves
    each net where its bound beats the stage's, with the bound of what served."""
    from hybrid_kinematics_ros.nodes.kinematics_node import KinematicsNode

    model = trained[1]
    overrides = [
        rclpy.parameter.Parameter("model_dir", value=str(trained[0])),
        rclpy.parameter.Parameter("out_of_range_policy", value=policy),
        rclpy.parameter.Parameter("publish_corrected_pose", value=False),
    ]
    node = KinematicsNode(f"range_{policy}", parameter_overrides=overrides)
    client = Client(f"range_{policy}_client")
    client.executor.add_node(node)
    outside = np.array([0.1, -1.0, model.trained_upper[2] + 0.01, -1.0, 1.0, 0.0])
    inside = np.array([0.1, -1.0, 1.0, -1.0, 1.0, 0.0])
    try:
        fk = client.service(ComputeFK, f"/range_{policy}/compute_fk")
        resp = client.call(fk, fk_request([inside, outside], model.joint_names))
        if policy == "refuse":
            assert not resp.success and "outside the calibrated joint range" in resp.message
            assert model.joint_names[2] in resp.message
        elif policy == "parametric":
            assert resp.success and list(resp.in_calibrated_range) == [True, False]
            np.testing.assert_allclose(poses_of(resp)[1], model.fk(outside, nets=False)[0], atol=1e-12)
            np.testing.assert_allclose(poses_of(resp)[0], model.fk(inside)[0], atol=1e-9)
        else:
            served = HybridModel.load(trained[0]).with_range_policy("bound")
            q = np.array([inside, outside])
            assert resp.success and list(resp.in_calibrated_range) == [True, False]
            assert "error bound is below the parametric stage's" in resp.message
            np.testing.assert_allclose(poses_of(resp), served.fk(q), atol=1e-9)
            np.testing.assert_allclose(resp.position_bound_mm, 1e3 * served.error_bounds(q)[0], rtol=1e-9)
        assert client.call(fk, fk_request([inside], model.joint_names)).success
    finally:
        client.close()
        node.destroy_node()


def test_coverage_radius(ros, trained):
    """With a coverage radius, a configuration inside every joint's range but far from the training data
    gets the model without the nets, and is flagged."""
    from hybrid_kinematics_ros.nodes.kinematics_node import KinematicsNode

    model = trained[1]
    near = np.load(trained[0] / "coverage.npy")[0].astype(float)
    far = 0.5 * (model.trained_lower + model.trained_upper)
    radius = 0.5 * float(model.coverage_distance(far)[0])
    overrides = [
        rclpy.parameter.Parameter("model_dir", value=str(trained[0])),
        rclpy.parameter.Parameter("out_of_range_policy", value="parametric"),
        rclpy.parameter.Parameter("coverage_radius_rad", value=radius),
        rclpy.parameter.Parameter("publish_corrected_pose", value=False),
    ]
    node = KinematicsNode("coverage", parameter_overrides=overrides)
    client = Client("coverage_client")
    client.executor.add_node(node)
    try:
        fk = client.service(ComputeFK, "/coverage/compute_fk")
        resp = client.call(fk, fk_request([near, far], model.joint_names))
        assert resp.success and list(resp.in_calibrated_range) == [True, False], resp.message
        np.testing.assert_allclose(poses_of(resp)[0], model.fk(near)[0], atol=1e-9)
        np.testing.assert_allclose(poses_of(resp)[1], model.fk(far, nets=False)[0], atol=1e-12)
    finally:
        client.close()
        node.destroy_node()
