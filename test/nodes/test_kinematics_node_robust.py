"""A node that never goes half-deaf: unexpected exceptions cost one answer, IK requests keep a total time
budget, IK solutions say whether they lie in the calibrated range, and /diagnostics reports the serving.

In-process nodes (real rclpy, one executor spinning the node, its companions and the client): a core
function is made to raise where no request can make it raise today."""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from std_srvs.srv import Trigger

from hybrid_kinematics_interfaces.srv import CompensateTrajectory, ComputeFK, ComputeIK
from hybrid_kinematics_ros.kinematics import se3
from test.nodes.rosutil import Client
from test.nodes.test_kinematics_node import fk_request, ik_request, poses_of

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def ros():
    rclpy.init()
    yield
    rclpy.shutdown()


def in_process(name: str, model_dir, **params):
    """A kinematics node and a client on one executor."""
    from hybrid_kinematics_ros.nodes.kinematics_node import KinematicsNode

    overrides = [rclpy.parameter.Parameter("model_dir", value=str(model_dir))]
    overrides += [rclpy.parameter.Parameter(k, value=v) for k, v in params.items()]
    node = KinematicsNode(name, parameter_overrides=overrides)
    client = Client(f"{name}_client")
    for n in (node, *node.companions):
        client.executor.add_node(n)
    return node, client


def raise_once(exc: Exception, then):
    calls = []

    def fail(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise exc
        return then(*args, **kwargs)

    return fail


def test_unexpected_exceptions_are_answered_and_every_service_keeps_serving(ros, trained, monkeypatch):
    node, client = in_process("robust", trained[0], publish_corrected_pose=False)
    model = node.model
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    T = model.fk(q)[0]
    try:
        fk = client.service(ComputeFK, "/robust/compute_fk")
        ik = client.service(ComputeIK, "/robust/compute_ik")
        reload = client.service(Trigger, "/robust/reload")
        # what no request reaches today: a LinAlgError deep in the solver, a bug in FK, a failing reload
        singular = np.linalg.LinAlgError("Singular matrix")
        monkeypatch.setattr(node.solver, "solve", raise_once(singular, node.solver.solve))
        monkeypatch.setattr(node.solver, "solve_many", raise_once(singular, node.solver.solve_many))
        monkeypatch.setattr(node, "_load", raise_once(MemoryError("cannot allocate"), node._load))
        for k in (1, 4):
            failed = client.call(ik, ik_request(T, q + 0.05, model.joint_names, k), resend_after=60)
            assert not failed.success and failed.message == "internal error (LinAlgError): Singular matrix"
            assert failed.solutions == [] and list(failed.in_calibrated_range) == []
            answered = client.call(ik, ik_request(T, q + 0.05, model.joint_names, k))
            assert answered.success, answered.message
        bug = IndexError("index 7 is out of bounds")
        monkeypatch.setattr(node.model, "fk_single", raise_once(bug, model.fk_single))
        bad_fk = client.call(fk, fk_request([q], model.joint_names), resend_after=60)
        assert not bad_fk.success and "IndexError" in bad_fk.message and "index 7" in bad_fk.message
        assert client.call(fk, fk_request([q], model.joint_names)).success
        bad_reload = client.call(reload, Trigger.Request(), resend_after=60)
        assert not bad_reload.success and "still serving the old model" in bad_reload.message
        assert "MemoryError" in bad_reload.message
        assert client.call(ik, ik_request(T, q + 0.05, model.joint_names)).success
        assert client.call(reload, Trigger.Request()).success
    finally:
        client.close()
        node.destroy_node()


def test_ik_request_budget_and_in_calibrated_range(ros, trained):
    model = trained[1]
    node, client = in_process("budget", trained[0], publish_corrected_pose=False, ik_request_budget_ms=1e-3)
    inside = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    outside = inside.copy()  # beyond the trained range, inside the joint limits
    j = int(np.argmax(model.chain.upper - model.trained_upper))
    outside[j] = 0.5 * (model.trained_upper[j] + model.chain.upper[j])
    assert not model.in_calibrated_range(outside)[0]
    try:
        ik = client.service(ComputeIK, "/budget/compute_ik")
        # a budget that is over before the first seed: an answer at once, not 65 seeds later
        starved = client.call(ik, ik_request(model.fk(inside)[0], inside, model.joint_names, 16))
        assert not starved.success and "time budget" in starved.message
        # one solution keeps the per-solution budget (ik_timeout_ms)
        for q, expected in ((inside, True), (outside, False)):
            resp = client.call(ik, ik_request(model.fk(q)[0], q, model.joint_names))
            assert resp.success, resp.message
            assert np.abs(np.array(resp.solutions[0].position) - q).max() < 1e-3
            assert list(resp.in_calibrated_range) == [expected]
    finally:
        client.close()
        node.destroy_node()


def test_diagnostics_report_the_serving(ros, trained):
    model = trained[1]
    node, client = in_process("diag", trained[0], publish_corrected_pose=False, diagnostics_period_s=0.2)
    inside = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    outside = inside.copy()
    outside[2] = model.trained_upper[2] + 0.05
    received: list[DiagnosticArray] = []
    client.node.create_subscription(DiagnosticArray, "/diagnostics", received.append, 10)
    try:
        fk = client.service(ComputeFK, "/diag/compute_fk")
        ik = client.service(ComputeIK, "/diag/compute_ik")
        for _ in range(3):
            assert client.call(fk, fk_request([inside, outside], model.joint_names), resend_after=60).success
        assert client.call(ik, ik_request(model.fk(inside)[0], inside, model.joint_names), resend_after=60).success

        def latest() -> dict[str, str] | None:
            for msg in reversed(received):
                for status in msg.status:
                    if status.name == "diag: hybrid kinematics":
                        return {kv.key: kv.value for kv in status.values}
            return None

        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and (latest() is None or latest()["ik_requests_served"] != "1"):
            client.spin_for(0.1)
        values = latest()
        assert values is not None, "no /diagnostics from the node"
        assert values["model"] == str(trained[0]) and values["range_policy"] == "warn"
        assert values["fk_requests_served"] == "3" and values["ik_requests_served"] == "1"
        assert values["out_of_range_count"] == "3"  # one configuration of each FK request
        p50, p90, p99 = (float(values[f"fk_latency_p{p}_ms"]) for p in (50, 90, 99))
        assert 0 < p50 <= p90 <= p99
        assert float(values["ik_latency_p50_ms"]) > 0
    finally:
        client.close()
        node.destroy_node()


def trajectory_request(t, q, names, qd=None, order=None):
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    order = list(range(len(names))) if order is None else order
    msg = JointTrajectory(joint_names=[names[i] for i in order])
    for k, tk in enumerate(t):
        point = JointTrajectoryPoint(positions=q[k, order].tolist())
        if qd is not None:
            point.velocities = qd[k, order].tolist()
        point.time_from_start = Duration(sec=int(tk), nanosec=round((tk - int(tk)) * 1e9))
        msg.points.append(point)
    req = CompensateTrajectory.Request()
    req.trajectory = msg
    return req


def test_compensate_trajectory_service(ros, trained):
    from hybrid_kinematics_ros.ik.compensate import compensate
    from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
    from test.ik.test_compensate import A, B, plan

    model = trained[1]
    node, client = in_process("comp", trained[0], publish_corrected_pose=False)
    t, q, qd, _ = plan(A, B, n=200)
    order = [3, 0, 5, 1, 4, 2]  # a planner's own joint order
    try:
        srv = client.service(CompensateTrajectory, "/comp/compensate_trajectory")
        resp = client.call(srv, trajectory_request(t, q, model.joint_names, qd, order))
        assert resp.success and resp.failed_index == -1, resp.message
        assert list(resp.trajectory.joint_names) == [model.joint_names[i] for i in order]
        got = np.array([p.positions for p in resp.trajectory.points])[:, np.argsort(order)]
        tight = IKOptions(position_tolerance_mm=1e-5, orientation_tolerance_deg=1e-5)  # the node's defaults
        expected = compensate(IKSolver(model, tight), q, t, qd)
        np.testing.assert_allclose(got, expected.positions, atol=1e-9)
        vel = np.array([p.velocities for p in resp.trajectory.points])[:, np.argsort(order)]
        np.testing.assert_allclose(vel, expected.velocities, atol=1e-9)
        stamps = [(p.time_from_start.sec, p.time_from_start.nanosec) for p in resp.trajectory.points]
        sent = trajectory_request(t, q, model.joint_names).trajectory.points
        assert stamps == [(p.time_from_start.sec, p.time_from_start.nanosec) for p in sent]
        assert max(resp.position_error_mm) <= 1e-5 and all(resp.in_calibrated_range)
        position, orientation = model.error_bounds(expected.positions)
        np.testing.assert_allclose(resp.position_bound_mm, 1e3 * position, rtol=1e-12)
        np.testing.assert_allclose(resp.orientation_bound_deg, np.degrees(orientation), rtol=1e-12)
        # the wrist crosses its singularity: corrected, or the first point that cannot be is named
        a, b = A.copy(), B.copy()
        a[4], b[4] = 0.6, -0.6
        t2, q2, _, _ = plan(a, b, n=401)
        singular = client.call(srv, trajectory_request(t2, q2, model.joint_names))
        if not singular.success:
            k = singular.failed_index
            assert k >= 0 and abs(q2[k, 4]) < 0.2 and f"point {k}" in singular.message
            assert len(singular.trajectory.points) == k
            per_point = ("position_error_mm", "orientation_error_deg", "in_calibrated_range", "position_bound_mm")
            assert {len(getattr(singular, name)) for name in per_point} == {k}  # each names the points returned
        bad = trajectory_request(t[:3], q[:3, :5], model.joint_names[:5])
        answer = client.call(srv, bad)
        assert not answer.success and "missing wrist_3_joint" in answer.message
        assert client.call(srv, trajectory_request(t, q, model.joint_names)).success  # still serving
    finally:
        client.close()
        node.destroy_node()


def test_condition_channels_come_from_parameters_settable_at_run_time(ros, thermal_models):
    """A model trained with the temperature channel serves with the node's conditions.temperature."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    from hybrid_kinematics_ros.model.hybrid import HybridModel

    path = thermal_models[0]["thermal"].path
    core = HybridModel.load(path)
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    node, client = in_process("thermal", path, publish_corrected_pose=False, **{"conditions.temperature": 27.0})

    def served():
        answer = client.call(fk, fk_request([q], core.joint_names))
        assert answer.success, answer.message
        return poses_of(answer)[0]

    def set_temperature(value: float):
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        request = SetParameters.Request(parameters=[Parameter(name="conditions.temperature", value=value)])
        return client.call(params, request).results[0]

    try:
        fk = client.service(ComputeFK, "/thermal/compute_fk")
        params = client.service(SetParameters, "/thermal/set_parameters")
        np.testing.assert_allclose(served(), core.with_condition("temperature", 27.0).fk(q)[0], atol=1e-9)
        assert set_temperature(19.0).successful
        at_19 = core.with_condition("temperature", 19.0).fk(q)[0]
        np.testing.assert_allclose(served(), at_19, atol=1e-9)
        refused = set_temperature(float("nan"))
        assert not refused.successful and "not a finite number" in refused.reason
        np.testing.assert_allclose(served(), at_19, atol=1e-9)  # still 19 °C
    finally:
        client.close()
        node.destroy_node()


def test_a_condition_set_during_an_ik_call_is_kept_and_the_ik_answers_for_its_own(ros, thermal_models, monkeypatch):
    """The node's threads share no mutable model: a temperature set while an IK runs (here from inside
    the call, once it has taken its model, so the interleaving is certain) serves every later answer, and the
    IK itself answers for the temperature it was asked with. An unset condition is named in every answer and
    in /diagnostics."""
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    path = thermal_models[0]["thermal"].path
    core = HybridModel.load(path)
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    node, client = in_process("midway", path, publish_corrected_pose=False)
    try:
        fk = client.service(ComputeFK, "/midway/compute_fk")
        answer = client.call(fk, fk_request([q], core.joint_names))
        assert answer.success and "conditions.temperature is not set, its training mean" in answer.message
        node.set_parameters([rclpy.parameter.Parameter("conditions.temperature", value=27.0)])
        with_model = node.solver.with_model

        def bind_while_the_temperature_changes(model):
            node.set_parameters([rclpy.parameter.Parameter("conditions.temperature", value=19.0)])
            return with_model(model)

        monkeypatch.setattr(node.solver, "with_model", bind_while_the_temperature_changes)
        at_27, at_19 = core.with_conditions([27.0]), core.with_conditions([19.0])
        target = at_27.fk(q + 0.02)[0]
        answer = client.call(client.service(ComputeIK, "/midway/compute_ik"), ik_request(target, q, core.joint_names))
        assert answer.success and "not set" not in answer.message, answer.message
        reached = at_27.fk(np.array(answer.solutions[0].position))[0]  # the IK answers for the 27 °C asked at
        assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 1e-6
        answer = client.call(fk, fk_request([q], core.joint_names))
        # and the temperature set meanwhile serves from then on
        np.testing.assert_allclose(poses_of(answer)[0], at_19.fk(q)[0], atol=1e-9)
        assert np.abs(poses_of(answer)[0] - at_27.fk(q)[0]).max() > 1e-6  # the two temperatures differ
    finally:
        client.close()
        node.destroy_node()


def test_gravity_parameter_serves_the_stage_for_another_mount(ros, thermal_models, tmp_path):
    """``gravity`` (m/s², base frame) serves a model whose model.json predates the gravity vector on a wall
    mount; one identified with another gravity, or a malformed value, stops the node with one line naming
    the parameter."""
    import json
    import shutil

    from hybrid_kinematics_ros.model.hybrid import HybridModel
    from hybrid_kinematics_ros.nodes.runtime import StartupError

    path = thermal_models[0]["thermal"].path
    old = tmp_path / "before_gravity"
    shutil.copytree(path, old)
    manifest = json.loads((old / "model.json").read_text())
    del manifest["parametric"]["payload"]["gravity"]
    (old / "model.json").write_text(json.dumps(manifest))
    core = HybridModel.load(old)
    np.testing.assert_array_equal(core.base.gravity, [0.0, 0.0, -9.81])  # an older model: a floor mount
    wall = np.array([-9.81, 0.0, 0.0])
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    node, client = in_process("wall", old, publish_corrected_pose=False, gravity=wall.tolist())
    try:
        answer = client.call(client.service(ComputeFK, "/wall/compute_fk"), fk_request([q], core.joint_names))
        np.testing.assert_allclose(poses_of(answer)[0], core.with_gravity(wall).fk(q)[0], atol=1e-9)
        assert np.abs(poses_of(answer)[0] - HybridModel.load(old).fk(q)[0]).max() > 1e-5  # the mount matters
    finally:
        client.close()
        node.destroy_node()
    with pytest.raises(StartupError, match=r"parameter gravity.*differs from the .* the model.s stage was identified"):
        in_process("othergravity", path, gravity=wall.tolist())
    with pytest.raises(StartupError, match="parameter gravity"):
        in_process("badgravity", path, gravity=[0.0, float("nan"), 1.0])


def test_payload_set_at_run_time_moves_the_stage_and_flags_the_nets(ros, thermal_models):
    """``payload_mass``/``payload_com`` set while serving: the stage's deflections follow the new payload,
    and every answer is flagged outside the calibrated range (the nets were trained with another). The
    payload used to be frozen in model.json."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    from hybrid_kinematics_ros.model.hybrid import HybridModel

    path = thermal_models[0]["thermal"].path
    core = HybridModel.load(path)
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    node, client = in_process("payload", path, publish_corrected_pose=False)
    try:
        fk = client.service(ComputeFK, "/payload/compute_fk")
        params = client.service(SetParameters, "/payload/set_parameters")
        before = client.call(fk, fk_request([q], core.joint_names))
        assert list(before.in_calibrated_range) == [True]
        mass = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=12.0)
        com = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=[0.0, 0.0, 0.1])
        request = SetParameters.Request(
            parameters=[Parameter(name="payload_com", value=com), Parameter(name="payload_mass", value=mass)]
        )
        results = client.call(params, request).results
        assert all(r.successful for r in results), [r.reason for r in results]
        after = client.call(fk, fk_request([q], core.joint_names))
        assert after.success and list(after.in_calibrated_range) == [False], after.message
        heavy = core.with_payload(12.0, np.array([0.0, 0.0, 0.1]))
        np.testing.assert_allclose(poses_of(after)[0], heavy.fk(q)[0], atol=1e-9)
        assert np.linalg.norm(poses_of(after)[0][:3, 3] - poses_of(before)[0][:3, 3]) > 1e-5  # the arm sags
        bad = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=-1.0)
        refused = client.call(params, SetParameters.Request(parameters=[Parameter(name="payload_mass", value=bad)]))
        assert not refused.results[0].successful and "mass >= 0" in refused.results[0].reason
        # a mass alone keeps the trained centre of mass; the trained payload again: inside the range again
        trained_mass, _ = core.trained_payload
        back = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=trained_mass)
        nan_com = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=[float("nan")] * 3)
        request = SetParameters.Request(
            parameters=[Parameter(name="payload_com", value=nan_com), Parameter(name="payload_mass", value=back)]
        )
        assert all(r.successful for r in client.call(params, request).results)
        assert list(client.call(fk, fk_request([q], core.joint_names)).in_calibrated_range) == [True]
        # and a heavy payload again for what follows
        request = SetParameters.Request(
            parameters=[Parameter(name="payload_com", value=com), Parameter(name="payload_mass", value=mass)]
        )
        assert all(r.successful for r in client.call(params, request).results)
        np.testing.assert_array_equal(
            poses_of(client.call(fk, fk_request([q], core.joint_names)))[0], poses_of(after)[0]
        )
    finally:
        client.close()
        node.destroy_node()


def test_concurrent_callers_each_get_the_answer_for_their_own_conditions(thermal_models):
    """Threads computing with different temperatures, and one trying approach directions over and over,
    each with its own value of one loaded model: each answer equals the one computed alone for its
    temperature, and the loaded model never changes."""
    import threading

    model = thermal_models[0]["thermal"]
    q = np.random.default_rng(3).uniform(-1.0, 0.0, (50, 6))
    expected = {}
    before = model.fk(q)
    for t in (15.0, 30.0):
        expected[t] = model.with_conditions([t]).fk(q)
    wrong: list[float] = []
    stop_at = time.monotonic() + 2.0

    def caller(t: float) -> None:
        while time.monotonic() < stop_at:
            if not np.array_equal(model.with_conditions([t]).fk(q), expected[t]):
                wrong.append(t)

    def trier() -> None:
        while time.monotonic() < stop_at:
            model.with_approach(np.ones(6)).fk(q[:1])

    threads = [threading.Thread(target=caller, args=(t,)) for t in (15.0, 30.0)] + [threading.Thread(target=trier)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not wrong
    assert not np.allclose(expected[15.0], expected[30.0])
    np.testing.assert_array_equal(model.fk(q), before)
    with pytest.raises(ValueError):
        model.condition_values[0] = 99.0  # read-only: a value, not a setting


def test_approach_directions_follow_the_joint_states(ros, backlash_models):
    """A model trained with approach directions serves with the directions the joints last moved in."""
    from sensor_msgs.msg import JointState

    from hybrid_kinematics_ros.model.hybrid import HybridModel

    path = backlash_models[0]["approach"].path
    core = HybridModel.load(path)
    topic = "/approach_test/joint_states"
    node, client = in_process("approach", path, publish_corrected_pose=False, joint_states_topic=topic)
    publisher = client.node.create_publisher(JointState, topic, 10)
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])

    def reach(joints: np.ndarray) -> None:  # publish until the node has taken it (discovery can be slow)
        msg = JointState(name=list(core.joint_names), position=joints.tolist())
        end = time.monotonic() + 60.0
        while time.monotonic() < end:
            publisher.publish(msg)
            for _ in range(5):
                client.executor.spin_once(timeout_sec=0.02)
            if node._latest is not None and np.array_equal(node._latest, joints):
                return
        raise TimeoutError("the node never received the joint states")

    def served() -> np.ndarray:
        answer = client.call(fk, fk_request([q], core.joint_names))
        assert answer.success, answer.message
        return poses_of(answer)[0]

    try:
        fk = client.service(ComputeFK, "/approach/compute_fk")
        reach(q - 0.01)
        reach(q)  # every joint came up from below
        up, down = core.with_approach(np.ones(6)), core.with_approach(-np.ones(6))
        rising = served()
        np.testing.assert_allclose(rising, up.fk(q)[0], atol=1e-9)
        reach(q + 0.01)
        reach(q)  # and now from above
        falling = served()
        np.testing.assert_allclose(falling, down.fk(q)[0], atol=1e-9)
        assert np.linalg.norm(falling[:3, 3] - rising[:3, 3]) > 0.2e-3  # m: the shoulder's backlash
        # IK from where the joints are (no seed: the latest joint states) answers for the directions the robot
        # will arrive in, every joint rising to a goal above, not for the falling ones it last moved in
        target = up.fk(q + 0.05)[0]
        answer = client.call(client.service(ComputeIK, "/approach/compute_ik"), ik_request(target))
        assert answer.success, answer.message
        solution = np.array(answer.solutions[0].position)
        assert se3.pose_errors(up.fk_single(solution), target)[0] < 1e-3  # mm
        assert se3.pose_errors(down.fk_single(solution), target)[0] > 0.1  # with the falling directions
        np.testing.assert_array_equal(served(), falling)  # and the node still serves the joints' own directions
    finally:
        client.close()
        node.destroy_node()
