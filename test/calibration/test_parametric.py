"""The parametric stage identifies the elasto-geometric model, says what it cannot identify and why,
and round-trips through the manifest."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import parametric
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import GEOMETRY_KINDS, fit_joint_map, identify
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.simulation.truth import TrueRobot


@pytest.fixture(scope="module")
def cell():
    """A UR10 whose truth the parametric model can represent exactly: no gear errors, linear springs."""
    cfg = load_robot_config("ur10")
    truth = dict(cfg.truth)
    truth["compliance"] = {**truth["compliance"], "cubic_ratio": 0.0}
    cfg = replace(cfg, truth=truth)
    robot = TrueRobot.from_config(cfg, enabled={"gear": False})
    q = np.random.default_rng(0).uniform(cfg.chain.lower, cfg.chain.upper, (2500, cfg.chain.dof))
    return cfg, robot, q, robot.fk(q)


@pytest.fixture(scope="module")
def identified(cell):
    cfg, _, q, T = cell
    return identify(cfg.chain, q, T, cfg.payload_mass, cfg.payload_com, max_pairs=1500)


def test_identified_model_matches_the_truth_it_can_represent(cell, identified):
    cfg, robot, _, _ = cell
    q = np.random.default_rng(1).uniform(cfg.chain.lower, cfg.chain.upper, (500, cfg.chain.dof))
    pos, rot = se3.pose_errors(robot.fk(q), identified.model.fk(q))
    nominal_pos, _ = se3.pose_errors(robot.fk(q), fk.fk(cfg.chain, q))
    assert nominal_pos.mean() > 1.0  # mm: there was something to identify
    # Fixing the unidentifiable parameters at zero is exact to first order only: the second-order
    # remainder of 1e-3 rad errors is ~1e-6 rad, far below any tracker's noise.
    assert pos.max() < 2e-3 and rot.max() < 2e-4  # mm and degrees, everywhere
    assert identified.rms_after["position_mm"] < 1e-3 < identified.rms_before["position_mm"]
    np.testing.assert_allclose(identified.model.compliance[1:5], robot.elastic.compliance[1:5], rtol=0.02)


def test_unidentifiable_parameters_are_reported_with_a_reason(identified):
    reasons = identified.reasons
    # joint 1 is vertical: gravity exerts no torque about it, so its spring never shows
    assert reasons["compliance shoulder_pan_joint"] == "does not change the measured poses"
    # turning joint 2's origin about its own axis is a zero offset of joint 2, which is kept
    assert "zero offset shoulder_lift_joint" in reasons["origin shoulder_lift_joint rz"]
    assert "zero offset shoulder_lift_joint" not in reasons
    kept = {p.name for p, ok in zip(identified.params, identified.identifiable, strict=True) if ok}
    assert not kept & set(reasons)
    assert len(kept) + len(reasons) == len(identified.params)


def test_position_only_identification(cell):
    cfg, robot, q, T = cell
    result = identify(cfg.chain, q, T, cfg.payload_mass, cfg.payload_com, position_only=True, max_pairs=1500)
    qt = np.random.default_rng(2).uniform(cfg.chain.lower, cfg.chain.upper, (300, cfg.chain.dof))
    pos, _ = se3.pose_errors(robot.fk(qt), result.model.fk(qt))
    assert pos.max() < 0.01  # mm
    assert "orientation_deg" not in result.rms_after
    assert result.reasons["flange rz"] == "does not change the measured positions"


def test_manifest_round_trip(cell, identified):
    cfg, _, q, _ = cell
    again = model_from_manifest(cfg.chain, identified.manifest())
    np.testing.assert_array_equal(again.fk(q[:50]), identified.model.fk(q[:50]))


def test_exported_urdf_carries_the_geometry_and_zero_offsets(cell, identified):
    """Re-parsed by the real URDF parser, the export equals the identified model without compliance."""
    from hybrid_kinematics_ros.calibration.export import export_urdf
    from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    cfg, _, q, T = cell
    model = HybridModel(cfg.chain, manifest={"parametric": identified.manifest()})
    text = export_urdf(model)
    exported = chain_from_urdf(text, cfg.chain.base_link, cfg.chain.tip_link).with_tool(cfg.chain.tool)
    rigid = model_from_manifest(cfg.chain, identified.manifest(), rigid=True)
    assert not rigid.is_elastic
    np.testing.assert_allclose(fk.fk(exported, q[:200]), rigid.fk(q[:200]), atol=1e-10)
    assert "_calibrated" in text and "compliance and the residual nets are not in this file" in text
    urdf_pos, _ = se3.pose_errors(T, fk.fk(exported, q))
    nominal_pos, _ = se3.pose_errors(T, fk.fk(cfg.chain, q))
    # on this compliant UR10 the geometry alone halves the error; compliance is the rest
    assert urdf_pos.mean() < nominal_pos.mean() / 1.5


def test_ik_through_the_parametric_model(cell, identified):
    """IK refines through the identified elastic model (its Jacobian holds the deflections fixed)."""
    from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    cfg, _, _, _ = cell
    model = HybridModel(cfg.chain, manifest={"parametric": identified.manifest()})
    solver = IKSolver(model, IKOptions(timeout_s=0.5))
    rng = np.random.default_rng(5)
    q_true = rng.uniform(cfg.chain.lower * 0.8, cfg.chain.upper * 0.8, (30, cfg.chain.dof))
    solved = 0
    for q in q_true:
        target = model.fk_single(q)
        result = solver.solve(target, q + rng.normal(0, 0.05, cfg.chain.dof))
        if result.success:
            solved += 1
            pos, rot = se3.pose_errors(model.fk_single(result.q)[None], target[None])
            assert pos[0] < 1e-4 and rot[0] < 1e-4
    assert solved >= 29


def _held_out(cfg, seed=11, count=400):
    return np.random.default_rng(seed).uniform(cfg.chain.lower, cfg.chain.upper, (count, cfg.chain.dof))


def test_cyclic_joint_errors_are_identified():
    """The virtual cell's gear errors (harmonics 1 and 2 of each joint angle) are cyclic joint errors:
    with harmonics the stage recovers them, without it they stay in the residual."""
    cfg = load_robot_config("ur10")
    robot = TrueRobot.from_config(cfg, enabled={"geometric": True, "gear": True, "compliance": False, "bending": False})
    q = np.random.default_rng(3).uniform(cfg.chain.lower, cfg.chain.upper, (1200, cfg.chain.dof))
    T = robot.fk(q)
    kinds = ("zero", "translation", "rotation", "harmonic")
    with_cyclic = identify(cfg.chain, q, T, kinds=kinds, harmonics=3, harmonic_prior=1e-3, map_step=0)
    without = identify(cfg.chain, q, T, kinds=kinds, harmonics=0, map_step=0)
    qt = _held_out(cfg)
    pos, _ = se3.pose_errors(robot.fk(qt), with_cyclic.model.fk(qt))
    pos0, _ = se3.pose_errors(robot.fk(qt), without.model.fk(qt))
    assert pos0.mean() > 0.1  # mm: the gear errors matter
    assert pos.mean() < pos0.mean() / 20
    # the joint-6 error (about the flange axis, nothing else looks like it): amp · sin(f q + phase)
    amp, phase = robot.gear_amplitude[5], robot.gear_phase[5]
    expected = np.column_stack([amp * np.cos(phase), amp * np.sin(phase)])  # sin and cos coefficients
    np.testing.assert_allclose(with_cyclic.model.joint_error[5, :2], expected, atol=0.05 * amp.max())
    assert (
        not with_cyclic.model.joint_error[:, 2].any()
        or np.abs(with_cyclic.model.joint_error[:, 2]).max() < 0.05 * amp.max()
    )


def test_tilted_joint_axis_is_covered_by_the_origin_rotations():
    """A joint axis that is not where the URDF says needs no parameter of its own: rotating the joint's
    origin tilts its axis, and the stage recovers the tilted robot."""
    from hybrid_kinematics_ros.kinematics.elastic import ElasticChain

    cfg = load_robot_config("ur10")
    axes = cfg.chain.axes.copy()
    axes[2] = axes[2] + np.array([np.radians(0.05), -np.radians(0.03), 0.0])  # joint 3 tilted by ~0.06°
    axes[2] /= np.linalg.norm(axes[2])
    truth = ElasticChain.rigid(replace(cfg.chain, axes=axes))
    q = np.random.default_rng(4).uniform(cfg.chain.lower, cfg.chain.upper, (600, cfg.chain.dof))
    result = identify(cfg.chain, q, truth.fk(q), kinds=GEOMETRY_KINDS)
    qt = _held_out(cfg)
    pos, rot = se3.pose_errors(truth.fk(qt), result.model.fk(qt))
    nominal, _ = se3.pose_errors(truth.fk(qt), fk.fk(cfg.chain, qt))
    assert nominal.mean() > 0.2  # mm
    assert pos.max() < 1e-3 and rot.max() < 1e-4  # mm, degrees


def test_geometry_only_calibration(cell, identified):
    """kinds=GEOMETRY_KINDS fits joint offsets and origins only (what robot_calibration gives); the full
    stage's geometry_model() is that same kind of model. On the compliant cell both leave the compliance."""
    cfg, robot, q, T = cell
    geometry = identify(cfg.chain, q, T, cfg.payload_mass, cfg.payload_com, max_pairs=1500, kinds=GEOMETRY_KINDS)
    assert not geometry.model.is_elastic and not geometry.model.has_joint_error
    assert geometry.reasons["compliance shoulder_lift_joint"] == "not fitted (kinds)"
    served = identified.geometry_model()
    assert not served.is_elastic and not served.has_joint_error
    qt = _held_out(cfg)
    truth = robot.fk(qt)
    full, _ = se3.pose_errors(truth, identified.model.fk(qt))
    geo, _ = se3.pose_errors(truth, geometry.model.fk(qt))
    geo_served, _ = se3.pose_errors(truth, served.fk(qt))
    assert full.mean() < geo.mean() / 100
    assert abs(geo_served.mean() - geo.mean()) < 0.1 * geo.mean()


def test_unknown_kind_is_refused(cell):
    cfg, _, q, T = cell
    with pytest.raises(CalibrationError, match="unknown parameter kinds"):
        identify(cfg.chain, q, T, kinds=("zero", "gear"))


def test_joint_error_map_learns_errors_too_short_for_the_harmonics():
    """Errors of 70 cycles per turn (beyond the Fourier series' harmonics) are left by the other
    parameters; the joint error map, fitted on one draw of poses, removes them on another."""
    cfg = load_robot_config("ur10")
    chain = cfg.chain
    coef = np.zeros((chain.dof, 70, 2))
    coef[1, 69, 0], coef[2, 69, 1], coef[4, 69, 0] = 3e-5, 2e-5, 4e-5  # rad: 4 to 8 arcseconds
    truth = replace(ElasticChain.rigid(chain), joint_error=coef)
    nominal = ElasticChain.rigid(chain)

    def draw(seed, count):
        return np.random.default_rng(seed).uniform(-1.2, 1.2, (count, chain.dof))

    q = draw(7, 3000)
    joint_map = fit_joint_map(nominal, q, truth.fk(q), position_only=False)
    qt = draw(8, 500)
    before, _ = se3.pose_errors(truth.fk(qt), nominal.fk(qt))
    after, _ = se3.pose_errors(truth.fk(qt), replace(nominal, joint_map=joint_map).fk(qt))
    assert before.mean() > 0.02  # mm
    assert after.mean() < before.mean() / 10
    # the map is the error itself: joint 2's at held-out angles, to a tenth of its amplitude
    np.testing.assert_allclose(joint_map(qt)[0][:, 1], 3e-5 * np.sin(70 * qt[:, 1]), atol=3e-6)
    # the dense Cholesky solve of its normal equations is scipy's sparse one, where the map is large
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(parametric, "DENSE_MAP_UNKNOWNS", 0)
        sparse_map = fit_joint_map(nominal, q, truth.fk(q), position_only=False)
    np.testing.assert_allclose(sparse_map.values, joint_map.values, rtol=0, atol=1e-9 * np.abs(joint_map.values).max())


def test_a_wall_mounted_robot_is_identified_with_its_own_gravity(cell, tmp_path):
    """Gravity along the base's −x (a wall mount): the stage identified with the robot config's gravity
    vector matches the truth, and it round-trips through model.json; with the floor's −z it cannot
    (gravity used to be −z of the base, whatever the mount)."""
    cfg, _, q, _ = cell
    wall = tmp_path / "wall.yaml"
    (tmp_path / "ur10.urdf").write_text(cfg.urdf_path.read_text())
    wall.write_text(cfg.path.read_text() + "\ngravity: [-9.81, 0.0, 0.0]\n")
    wall_cfg = replace(load_robot_config(wall), truth=cfg.truth)
    np.testing.assert_array_equal(wall_cfg.gravity, [-9.81, 0.0, 0.0])
    robot = TrueRobot.from_config(wall_cfg, enabled={"gear": False})
    T = robot.fk(q)
    test_q = np.random.default_rng(1).uniform(cfg.chain.lower, cfg.chain.upper, (300, cfg.chain.dof))
    result = identify(cfg.chain, q, T, cfg.payload_mass, cfg.payload_com, max_pairs=1500, gravity=wall_cfg.gravity)
    pos, _ = se3.pose_errors(robot.fk(test_q), result.model.fk(test_q))
    assert pos.max() < 2e-3  # mm
    served = model_from_manifest(cfg.chain, result.manifest())
    np.testing.assert_array_equal(served.gravity, wall_cfg.gravity)
    np.testing.assert_allclose(served.fk(test_q), result.model.fk(test_q), atol=1e-12)
    single = np.array([served.fk_single(x) for x in test_q[:5]])
    np.testing.assert_allclose(single, served.fk(test_q[:5]), atol=1e-12)
    floor = identify(cfg.chain, q, T, cfg.payload_mass, cfg.payload_com, max_pairs=1500)
    assert se3.pose_errors(robot.fk(test_q), floor.model.fk(test_q))[0].mean() > 20 * pos.mean()
