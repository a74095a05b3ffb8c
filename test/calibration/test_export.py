"""The calibration in the files users keep: URDF, UR kinematics file and DH table, each read back and judged
on held-out pairs beside the full model, with what it leaves behind."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.export import export, split_along_axis
from hybrid_kinematics_ros.io.pairs import write_pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.dh import dh_fk, dh_table
from hybrid_kinematics_ros.kinematics.ur_kinematics import read_ur_kinematics, urdf_from_ur_kinematics
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from test.cli.inprocess import cli


def test_the_ur_kinematics_file_reads_back_as_the_exported_geometry(shoulder_model, tmp_path):
    _, model, te, _ = shoulder_model
    exported = export(model, "ur-kinematics")
    path = tmp_path / "ur10_calibrated.yaml"
    path.write_text(exported.text)
    kinematics = read_ur_kinematics(path)
    assert kinematics.kinematics_hash.startswith("calib_hkr_")
    # the file built the way ur_description's xacro builds it, from its base_link_inertia (the embedded
    # UR10's base link) to tool0, against the geometry the export says it holds
    text = urdf_from_ur_kinematics(kinematics, model.chain.urdf_text)
    read = chain_from_urdf(text, "base_link_inertia", "tool0")
    exported_tip = fk.fk(exported.chain, te.q[:50])
    position, angle = se3.pose_errors(fk.fk(read, te.q[:50]) @ _tool0_turn(read, exported.chain), exported_tip)
    assert position.max() < 1e-6 and angle.max() < 1e-6  # mm, deg
    # what it cannot hold is named: the flange correction across wrist 3's axis, the elastic terms and the nets
    assert any("flange" in item for item in exported.left) and any("nets" in item for item in exported.left)


def test_the_ur_file_differs_from_the_stage_only_by_the_flange_correction_across_wrist_3(shoulder_model):
    _, model, te, _ = shoulder_model
    chain = model.chain
    geometry = model_from_manifest(chain, model.manifest["parametric"], rigid=True)
    flange = se3.inverse(chain.post) @ geometry.chain.post
    _, across = split_along_axis(chain.post @ flange @ se3.inverse(chain.post), chain.axes[-1])
    exported = export(model, "ur-kinematics")
    restored = fk.fk(exported.chain, te.q) @ se3.inverse(chain.post) @ across @ chain.post
    position, angle = se3.pose_errors(restored, geometry.fk(te.q))
    assert position.max() < 1e-6 and angle.max() < 1e-6  # mm, deg
    # the correction it prints, appended at the tip as a TCP, restores the stage's geometry
    with_tcp = fk.fk(exported.chain.with_tool(exported.tip_correction), te.q)
    position, angle = se3.pose_errors(with_tcp, geometry.fk(te.q))
    assert position.max() < 1e-6 and angle.max() < 1e-6


def test_a_correction_splits_into_a_part_that_commutes_with_the_joint_and_one_across_its_axis():
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    correction = se3.from_rotvec(rng.normal(scale=0.003, size=(1, 3)), rng.normal(scale=0.02, size=(1, 3)))[0]
    along, across = split_along_axis(correction, axis)
    assert np.allclose(along @ across, correction, atol=1e-12)
    turn = se3.from_rotvec(np.zeros((1, 3)), (0.7 * axis)[None])[0]  # the joint moving about its axis
    assert np.allclose(along @ turn, turn @ along, atol=1e-12)
    assert abs(np.dot(across[:3, 3], axis)) < 1e-12
    assert abs(np.dot(Rotation.from_matrix(across[:3, :3]).as_rotvec(), axis)) < 1e-12


def _tool0_turn(read, exported) -> np.ndarray:
    """ur_description's tool0 against the embedded URDF's: a fixed rotation, the same at every pose."""
    q = np.zeros((1, exported.dof))
    return se3.inverse(fk.fk(read, q)[0]) @ fk.fk(exported, q)[0]


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_the_dh_table_holds_the_calibrated_geometry(shoulder_model, convention):
    _, model, te, _ = shoulder_model
    exported = export(model, "dh", convention)
    assert convention in exported.text
    table = dh_table(exported.chain, convention)
    geometry = model_from_manifest(model.chain, model.manifest["parametric"], rigid=True)
    position, _ = se3.pose_errors(dh_fk(table, te.q[:50]), geometry.fk(te.q[:50]))
    assert position.max() < 1e-6  # mm: the table is the stage's geometry, not the nominal one
    assert any("parallel" in note for note in exported.left)  # the UR10's shoulder, elbow and wrist 1


def test_export_prints_each_files_held_out_error_beside_the_full_models(shoulder_model, tmp_path):
    model_dir, _, te, _ = shoulder_model
    bag = tmp_path / "held_out"
    write_pairs(bag, te)
    reports = {}
    for form in ("urdf", "ur-kinematics", "dh"):
        out = tmp_path / f"calibrated.{form}"
        result = cli("export", "--model", str(model_dir), "--format", form, "--out", str(out), "--bag", str(bag))
        assert result.returncode == 0, result.stderr
        assert "kinematics node" in result.stderr and "compensate" in result.stderr
        reports[form] = json.loads(result.stdout)
    for report in reports.values():
        assert report["hybrid"]["position_mm_mean"] < report["exported"]["position_mm_mean"]
        assert report["exported"]["position_mm_mean"] < report["nominal"]["position_mm_mean"]
    assert reports["dh"]["exported"] == reports["urdf"]["exported"]  # the same geometry
    again = cli("export", "--model", str(model_dir), "--format", "dh", "--out", str(tmp_path / "calibrated.dh"))
    assert again.returncode == 2 and "exists already" in again.stderr
